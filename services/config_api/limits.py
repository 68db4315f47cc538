"""What every request meets before any handler (ASGI middleware), in this order: a write without the
token gets 401 before its body is read (:class:`WritesNeedTheToken`), a larger body than the limit
413 (:class:`BodySizeLimit`)."""

from __future__ import annotations

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.config_api.dependencies import UNAUTHORIZED, UNAUTHORIZED_HEADERS, token_matches

#: The methods that change something: every route with one of them needs the token.
WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


class WritesNeedTheToken:
    """A write request (:data:`WRITE_METHODS`) without ``Authorization: Bearer <token>`` gets 401 at
    once: its body is never read, parsed nor validated for a client that may not write (without it
    a malformed body or header got 422 first, an oversized one 413). The routes' own check (``require_writer``) stays: it
    documents the security in the OpenAPI schema and names the actor."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] in WRITE_METHODS:
            scheme, _, presented = dict(scope["headers"]).get(b"authorization", b"").decode("latin-1").partition(" ")
            if scheme.lower() != "bearer" or not token_matches(presented.strip(), self.token):
                await JSONResponse({"detail": UNAUTHORIZED}, status_code=401, headers=UNAUTHORIZED_HEADERS)(
                    scope, receive, send)
                return
        await self.app(scope, receive, send)


class BodySizeLimit:
    """Reads the whole body (at most ``max_bytes``) up front and replays it to the app.

    A declared ``Content-Length`` above the limit is refused without reading; a chunked body is
    refused as soon as it grows past the limit.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.max_bytes):
            await self._refuse(scope, receive, send, 413 if declared.isdigit() else 400)
            return
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            body += message.get("body", b"")
            if len(body) > self.max_bytes:
                await self._refuse(scope, receive, send, 413)
                return
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if replayed:
                return await receive()
            replayed = True
            return {"type": "http.request", "body": bytes(body), "more_body": False}

        await self.app(scope, replay, send)

    async def _refuse(self, scope: Scope, receive: Receive, send: Send, code: int) -> None:
        detail = f"request body larger than {self.max_bytes} bytes" if code == 413 else "invalid Content-Length"
        await JSONResponse({"detail": detail}, status_code=code, headers={"Connection": "close"})(scope, receive, send)
