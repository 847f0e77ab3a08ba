"""Typed dependencies of the HTTP routes (the style of FastAPI's full-stack template): the
routers are module-level and get the app's service, its frame workers and the token check
from here."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from service.engine.localization_service import LocalizationService


def get_service(request: Request) -> LocalizationService:
    """The ``LocalizationService`` of the app that serves the request."""
    return request.app.state.service


ServiceDep = Annotated[LocalizationService, Depends(get_service)]
