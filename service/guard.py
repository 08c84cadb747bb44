"""ASGI middleware in front of every route: API-key check and request-body size caps.

It sits below FastAPI so that it sees the raw byte stream: an oversized body is refused
with 413 as soon as its Content-Length (or, without one, its running byte count) passes
the cap, before the route buffers or parses anything. After answering early it reads and
discards up to `DRAIN_LIMIT` more bytes, so that an ordinary HTTP/1.1 client that is still
sending gets to read the answer instead of a reset connection.
"""

from __future__ import annotations

import hmac
import json
from typing import Any, Awaitable, Callable

from .settings import Settings

Scope = dict[str, Any]
Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

DRAIN_LIMIT = 64 << 20
OPEN_PATHS = ("/health", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json")
OPEN_PATHS += ("/", "/ui", "/ui/", "/ui/app.js", "/ui/app.css")   # the page's static files; its API calls send the key
UPLOAD_PATH = "/v1/models"


def error_body(code: str, message: str, field: str | None = None) -> bytes:
    return json.dumps({"error": {"code": code, "message": message, "field": field}}).encode()


class Guard:
    def __init__(self, app: ASGIApp, settings: Settings):
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if self.settings.api_key is not None and scope["path"] not in OPEN_PATHS:
            if not _authorized(headers.get("authorization"), self.settings.api_key):
                await _answer(send, 401, error_body("unauthorized", "missing or wrong API key: send "
                              "'Authorization: Bearer <key>'", "Authorization"), {"www-authenticate": "Bearer"})
                await _drain(receive, DRAIN_LIMIT)
                return
        is_upload = scope["method"] == "POST" and scope["path"].rstrip("/") == UPLOAD_PATH
        cap = self.settings.max_upload_bytes if is_upload else self.settings.max_json_bytes
        what = "model upload" if is_upload else "request body"
        field = "file" if is_upload else None
        too_large = error_body("payload_too_large", f"the {what} exceeds the cap of {cap} bytes", field)
        length = headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > cap:
            await _answer(send, 413, too_large)
            await _drain(receive, DRAIN_LIMIT)
            return

        received = 0
        answered = False

        async def limited_receive() -> Message:
            nonlocal received, answered
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > cap and not answered:
                    answered = True
                    await _answer(send, 413, too_large)
                    if message.get("more_body", False):
                        await _drain(receive, DRAIN_LIMIT)
                    return {"type": "http.disconnect"}  # the route stops reading and cleans up
            return message

        async def guarded_send(message: Message) -> None:
            if not answered:  # once the 413 went out, the route's own answer is dropped
                await send(message)

        await self.app(scope, limited_receive, guarded_send)


def _authorized(header: str | None, key: str) -> bool:
    if header is None:
        return False
    scheme, _, token = header.partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(token.strip().encode(), key.encode())


async def _answer(send: Send, status: int, body: bytes, headers: dict[str, str] | None = None) -> None:
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


async def _drain(receive: Receive, limit: int) -> None:
    """Read and discard the rest of the request body, at most `limit` bytes."""
    drained = 0
    while drained <= limit:
        message = await receive()
        if message["type"] != "http.request":
            return
        drained += len(message.get("body", b""))
        if not message.get("more_body", False):
            return
