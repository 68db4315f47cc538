"""The FastAPI application: routers, the injected context, body size limit, optional CORS."""

from __future__ import annotations

import math

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from services.config_api.dependencies import ApiContext
from services.config_api.limits import BodySizeLimit
from services.config_api.routers import calibrate, config, console, status
from services.config_api.routers.console import STATIC_DIR
from services.config_api.store import StoreError
from shared.version import VERSION


async def _store_error(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": f"not applied: {exc}"}, status_code=503)


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    """FastAPI's 422, except that a NaN/Inf the client sent is echoed as text (JSON has no NaN)."""
    assert isinstance(exc, RequestValidationError)
    finite = {float: lambda x: x if math.isfinite(x) else repr(x)}
    return JSONResponse({"detail": jsonable_encoder(exc.errors(), custom_encoder=finite)}, status_code=422)


def create_app(context: ApiContext) -> FastAPI:
    """The app serving ``context`` (built by the caller, which owns the bus and the store)."""
    app = FastAPI(
        title="safemimic config API",
        version=VERSION,
        description=(
            "The single writer of the stack's parameters (architecture §1). Writes need "
            "`Authorization: Bearer <token>`; every accepted change is persisted with a new version, "
            "published on Zenoh as ConfigUpdate and acknowledged by the safety service's SafetyStatus."
        ),
    )
    app.state.context = context
    for module in (config, calibrate, status, console):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.add_exception_handler(StoreError, _store_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    if context.settings.cors_origins:
        app.add_middleware(
            CORSMiddleware, allow_origins=context.settings.cors_origins,
            allow_methods=["GET", "PATCH", "POST"], allow_headers=["Authorization", "Content-Type", "X-Operator"],
        )
    app.add_middleware(BodySizeLimit, max_bytes=context.settings.max_body_bytes)
    return app
