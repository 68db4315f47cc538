"""The FastAPI application: routers, the injected context, body size limit, optional CORS."""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from services.config_api.dependencies import ApiContext
from services.config_api.limits import BodySizeLimit, WritesNeedTheToken
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


def _velocity_schema(schema: dict[str, Any], limits: list[float]) -> dict[str, Any]:
    """``schema`` (the generated OpenAPI) with ``SafetyPatch``'s ``u_max`` / ``u_min`` bounded per joint
    by the robot's ``joint_velocity_limits`` (rad/s) instead of the request model's static range, so
    that the schema says what the writer accepts (:mod:`services.config_api.writer`)."""
    fields = schema["components"]["schemas"]["SafetyPatch"]["properties"]
    for name, bound in (("u_max", "maximum"), ("u_min", "minimum")):
        field = fields[name]
        for variant in field.get("anyOf", [field]):
            if variant.get("type") == "array":
                static = variant.pop("items")
                sign = 1.0 if bound == "maximum" else -1.0
                variant["prefixItems"] = [{**static, bound: sign * min(abs(static[bound]), limit)} for limit in limits]
                variant["items"] = False
    return schema


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
    app.add_middleware(WritesNeedTheToken, token=context.token)  # outermost (added last): no body read without it
    served = None

    def openapi() -> dict[str, Any]:
        nonlocal served
        if served is None:
            served = app.openapi_schema = _velocity_schema(get_openapi(
                title=app.title, version=app.version, description=app.description, routes=app.routes),
                context.writer.spec.velocity_limits())
        return served

    app.openapi = openapi  # type: ignore[method-assign]
    return app
