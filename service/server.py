"""Assemble and run the service: maps, engine, HTTP app, Zenoh bridge, uvicorn."""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import threading
import time
from collections.abc import Iterator

import uvicorn
from fastapi import FastAPI

from service.engine.localization_service import LocalizationService
from service.http.app import create_app
from service.http.limits import limited_protocol
from service.settings import Settings
from service.zenoh.bridge import ZenohBridge, check_security

log = logging.getLogger("swarmloc")


class _Server(uvicorn.Server):
    """uvicorn with a bounded, draining shutdown: new frames get 503 at once, frames in
    flight get ``shutdown_deadline_s`` (uvicorn's graceful timeout) and the open event
    streams (GET /events) are ended, since they never end by themselves."""

    def __init__(self, config: uvicorn.Config, service: LocalizationService) -> None:
        super().__init__(config)
        self._service = service

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self._service.begin_shutdown()
        self._service.events.close()
        await super().shutdown(sockets)
        # frames have stopped: the in-process store writes its snapshot (if configured);
        # here, not after run(): uvicorn re-raises SIGTERM when it returns
        self._service.close()


def _uvicorn_config(app: FastAPI, settings: Settings, log_level: str) -> uvicorn.Config:
    return uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level,
                          timeout_graceful_shutdown=math.ceil(settings.shutdown_deadline_s),
                          http=limited_protocol(settings.http_max_header_bytes,
                                                settings.http_read_timeout_s))


def build_app(settings: Settings) -> FastAPI:
    if settings.zenoh_enabled:
        check_security(settings)  # refuse before loading maps, with the reason
    service = LocalizationService(settings)
    hooks = [ZenohBridge(service)] if settings.zenoh_enabled else []
    return create_app(service, lifespan_hooks=hooks)


def limit_native_threads(settings: Settings) -> None:
    """Robots run in parallel threads: one BLAS thread each and ``opencv_threads`` OpenCV
    threads, not pools of threads per call fighting over the cores (OpenCV's idle workers
    spin after each parallel call and delay the threads that answer the robots). Process-wide;
    features and estimates do not depend on it."""
    import cv2
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, "blas")
    if settings.opencv_threads:
        cv2.setNumThreads(settings.opencv_threads)


def run(settings: Settings) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    from service.vision.matcher import warm_up

    limit_native_threads(settings)
    warm_up()  # compile (or load) the matcher's kernels before the first frame
    app = build_app(settings)
    log.info("maps loaded from %s: %s", settings.maps_dir, sorted(app.state.service.maps))
    _Server(_uvicorn_config(app, settings, "info"), app.state.service).run()


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_server(service: LocalizationService, zenoh: bool = True,
                   timeout_s: float = 20.0) -> Iterator[str]:
    """uvicorn (and the Zenoh bridge) for ``service`` in a background thread; yields the base
    URL and stops the server on exit. Used by the latency benchmark and the tests."""
    s = service.settings
    hooks = [ZenohBridge(service)] if zenoh else []
    server = _Server(_uvicorn_config(create_app(service, lifespan_hooks=hooks), s, "warning"),
                     service)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            server.should_exit = True
            raise RuntimeError(f"the server did not start on {s.host}:{s.port}")
        time.sleep(0.05)
    try:
        yield f"http://{s.host}:{s.port}"
    finally:
        server.should_exit = True
        thread.join(timeout=timeout_s)
