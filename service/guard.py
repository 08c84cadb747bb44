"""ASGI middleware in front of every route: API keys, header and body size caps, body timeouts,
security headers, and the last word on unexpected errors.

It sits below FastAPI so that it sees the raw byte stream: headers past `MAX_HEADER_BYTES` get
431 (h11 refuses those that are still incomplete at that size: service.timeouts); an oversized
body is refused with 413 as soon as its Content-Length (or, without one, its running byte
count) passes the cap, before the route buffers or parses anything; a body that pauses longer
than `body_timeout`, or trickles (it may take `body_timeout` seconds plus one second per
`min_body_rate` bytes received), gets 408. After answering early it reads and discards up to
`DRAIN_LIMIT` more bytes, so that an ordinary HTTP/1.1 client that is still sending gets to
read the answer instead of a reset connection. The caller's `Principal` (service.keys) goes into
`scope["state"]["principal"]`. An exception no handler turned into an answer becomes a
JSON 500 here, so the connection stays alive (uvicorn closes it when an exception reaches it).
"""

from __future__ import annotations

import asyncio
import logging
import re
from typing import Any, Awaitable, Callable

from .errors import error_body
from .keys import KeyRing
from .settings import Settings

log = logging.getLogger("phd.service")

Scope = dict[str, Any]
Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

DRAIN_LIMIT = 64 << 20
MAX_HEADER_BYTES = 64 * 1024
OPEN_PATHS: tuple[str, ...] = ("/health", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json")
OPEN_PATHS += ("/", "/ui", "/favicon.ico")
OPEN_PREFIXES = ("/ui/", "/docs-assets/")   # the page's and the docs' static files; the page's API calls send the key
UPLOAD_PATHS = re.compile(r"^/v1/(models|captures|captures/[^/]+/photos)/?$")   # multipart bodies
DOC_PATHS = ("/docs", "/docs/oauth2-redirect", "/redoc")   # FastAPI's pages start their scripts inline
# Same-origin files only (the web page: HTML, one JS and one CSS file, images from the API or
# blob:/data: URLs), no inline script or style, no frames, no plugins.
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
       "font-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
SECURITY_HEADERS = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY"),
                    (b"referrer-policy", b"no-referrer"), (b"cross-origin-opener-policy", b"same-origin"),
                    (b"permissions-policy", b"camera=(), microphone=(), geolocation=()")]
ANSWER_HEADERS = SECURITY_HEADERS + [(b"content-security-policy", CSP.encode())]


class Guard:
    def __init__(self, app: ASGIApp, settings: Settings, keys: KeyRing):
        self.app = app
        self.settings = settings
        self.keys = keys

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def secured_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                extra = SECURITY_HEADERS if scope["path"] in DOC_PATHS else ANSWER_HEADERS
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        try:
            await self.guard(scope, receive, secured_send)
        except Exception:  # a bug: answer 500 as JSON and keep the connection (uvicorn would drop it)
            log.exception("unexpected error in %s %s", scope["method"], scope["path"])
            if not started:
                await _answer(secured_send, 500, error_body("internal_error", "unexpected error; see the server log"))

    async def guard(self, scope: Scope, receive: Receive, send: Send) -> None:
        header_bytes = sum(len(k) + len(v) + 4 for k, v in scope["headers"])   # b"name: value\r\n"
        if header_bytes > MAX_HEADER_BYTES:
            largest = max(scope["headers"], key=lambda kv: len(kv[0]) + len(kv[1]))[0].decode("latin-1")
            await _answer(send, 431, error_body("headers_too_large", f"the request headers take {header_bytes} bytes, "
                          f"over the cap of {MAX_HEADER_BYTES}; the largest is '{largest}'", largest))
            await _drain(receive, DRAIN_LIMIT)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        principal = self.keys.identify(headers.get("authorization"))
        is_open = scope["path"] in OPEN_PATHS or scope["path"].startswith(OPEN_PREFIXES)
        if principal is None and not is_open and scope["method"] != "OPTIONS":
            await _answer(send, 401, error_body("unauthorized", "missing or wrong API key: send "
                          "'Authorization: Bearer <key>'", "Authorization"), {"www-authenticate": "Bearer"})
            await _drain(receive, DRAIN_LIMIT)
            return
        scope.setdefault("state", {})["principal"] = principal
        upload = UPLOAD_PATHS.match(scope["path"]) if scope["method"] == "POST" else None
        is_upload = upload is not None
        cap = self.settings.max_upload_bytes if is_upload else self.settings.max_json_bytes
        models = upload is not None and upload.group(1) == "models"
        what = "model upload" if models else "photo upload" if is_upload else "request body"
        field = "file" if models else "photos" if is_upload else None
        too_large = error_body("payload_too_large", f"the {what} exceeds the cap of {cap} bytes", field)
        length = headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > cap:
            await _answer(send, 413, too_large)
            await _drain(receive, DRAIN_LIMIT)
            return

        received = 0
        answered = False
        body_done = False
        loop = asyncio.get_running_loop()
        start = loop.time()
        pause, rate = self.settings.body_timeout, self.settings.min_body_rate

        async def limited_receive() -> Message:
            nonlocal received, answered, body_done
            if body_done:
                return await receive()       # after the body only a disconnect can come: no deadline
            left = start + pause + received / rate - loop.time()     # the whole body's deadline so far
            try:
                message = await asyncio.wait_for(receive(), max(min(pause, left), 0.0))
            except asyncio.TimeoutError:
                if not answered:
                    answered = True
                    why = (f"paused for more than {pause:g} seconds" if left > pause else f"arrived slower than "
                           f"{rate:g} bytes per second ({received} bytes in {loop.time() - start:.1f} seconds)")
                    await _answer(send, 408, error_body("request_timeout", f"the request body {why}", field),
                                  {"connection": "close"})
                return {"type": "http.disconnect"}
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
                if received > cap and not answered:
                    answered = True
                    await _answer(send, 413, too_large)
                    if message.get("more_body", False):
                        await _drain(receive, DRAIN_LIMIT)
                    return {"type": "http.disconnect"}  # the route stops reading and cleans up
            else:
                body_done = True
            return message

        async def guarded_send(message: Message) -> None:
            if not answered:  # once the 413 or 408 went out, the route's own answer is dropped
                await send(message)

        await self.app(scope, limited_receive, guarded_send)


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
