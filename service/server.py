"""Assemble and run the service: maps, engine, HTTP app, Zenoh bridge, uvicorn."""

from __future__ import annotations

import logging

import uvicorn
from fastapi import FastAPI

from service.http_api import create_app
from service.sessions import LocalizationService
from service.settings import Settings
from service.zenoh_bridge import ZenohBridge

log = logging.getLogger("swarmloc")


def build_app(settings: Settings) -> FastAPI:
    service = LocalizationService(settings)
    for name, err in service.load_errors.items():
        log.warning("map %s not loaded: %s", name, err)
    hooks = [ZenohBridge(service)] if settings.zenoh_enabled else []
    return create_app(service, lifespan_hooks=hooks)


def run(settings: Settings) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    app = build_app(settings)
    log.info("maps loaded from %s: %s", settings.maps_dir, sorted(app.state.service.maps))
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="info")
