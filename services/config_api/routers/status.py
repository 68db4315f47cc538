"""``/api/status``, its live stream (server-sent events) and ``/api/health``."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

from fastapi import APIRouter, Depends, Request
from fastapi.responses import StreamingResponse

from services.config_api.dependencies import ApiContext, Context, allow_read
from services.config_api.models import HealthResponse, StatusResponse
from services.config_api.routers import READ_ERRORS, READ_OPENAPI

router = APIRouter(prefix="/api", tags=["status"])
#: A comment line this often keeps proxies from closing an idle stream (s).
_KEEPALIVE_S = 5.0


def current_status(context: ApiContext) -> StatusResponse:
    return StatusResponse.build(
        context.link.status.get(), context.link.human.get(), context.store.snapshot.version, time.monotonic()
    )


@router.get(
    "/status", response_model=StatusResponse, dependencies=[Depends(allow_read)], responses=READ_ERRORS,
    openapi_extra=READ_OPENAPI,
)
async def get_status(context: Context) -> StatusResponse:
    """The newest SafetyStatus from Zenoh (mode, h_min_self, h_min_human, active constraints, solve
    time, applied config version) and the age of the newest human state."""
    return current_status(context)


async def _events(request: Request, context: ApiContext) -> AsyncIterator[str]:
    """``status`` events at most ``api.stream_rate_hz`` (only when a new SafetyStatus arrived),
    a ``config`` event whenever the configuration version changes (and first thing)."""
    period = 1.0 / context.settings.stream_rate_hz
    last_status = None
    last_version = None
    last_sent = time.monotonic()
    while not await request.is_disconnected():
        version = context.store.snapshot.version
        if version != last_version:
            last_version = version
            last_sent = time.monotonic()
            yield f"event: config\ndata: {{\"version\": {version}}}\n\n"
        newest = context.link.status.get()
        if newest is not None and newest is not last_status:
            last_status = newest
            last_sent = time.monotonic()
            yield f"event: status\ndata: {current_status(context).model_dump_json()}\n\n"
        elif time.monotonic() - last_sent > _KEEPALIVE_S:
            last_sent = time.monotonic()
            yield ": keep-alive\n\n"
        await asyncio.sleep(period)


@router.get(
    "/status/stream",
    dependencies=[Depends(allow_read)],
    response_class=StreamingResponse,
    openapi_extra=READ_OPENAPI,
    responses={200: {"content": {"text/event-stream": {}}, "description": "server-sent events: status, config"}, **READ_ERRORS},
)
async def stream_status(request: Request, context: Context) -> StreamingResponse:
    """Live status as server-sent events: ``event: status`` (a StatusResponse as JSON) whenever a new
    SafetyStatus arrived (at most ``api.stream_rate_hz``), ``event: config`` (``{"version": n}``)
    when the configuration changes."""
    return StreamingResponse(
        _events(request, context), media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


@router.get(
    "/health", response_model=HealthResponse, dependencies=[Depends(allow_read)], responses=READ_ERRORS,
    openapi_extra=READ_OPENAPI,
)
async def health(context: Context) -> HealthResponse:
    """Liveness of the API: configuration version, uptime, services seen alive on Zenoh."""
    return HealthResponse(
        config_version=context.store.snapshot.version, uptime_s=time.monotonic() - context.started,
        services_alive=context.link.services_alive, store=str(context.store.path),
    )
