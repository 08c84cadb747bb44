"""A multipart body read as it arrives, part by part, for every upload route (models, a
capture's photos).

python-multipart's streaming parser calls back with headers and bytes; `read_parts` turns that
into one question per part, asked when its headers are in: where do its bytes go (`Sink`)? The
caller's sink counts, caps and writes them (a file in the data directory, or a small buffer),
so a body never sits in memory whole. What every upload answers the same way lives here: a
body that is not multipart (415), a refused boundary or a malformed body (400), a client that
disconnects mid-body (400), and a full disk while writing (507, through `service.store.writing`).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

from python_multipart import MultipartParser
from python_multipart.exceptions import FormParserError
from python_multipart.multipart import parse_options_header
from starlette.requests import ClientDisconnect, Request

from .errors import ServiceError, insufficient_storage
from .store import writing


@dataclass
class Part:
    """One part's headers: its form field name and file name."""

    name: str
    filename: str | None


class Sink(Protocol):
    """Where one part's bytes go: `write` each chunk (raising a ServiceError past a cap), then `close`."""

    def write(self, chunk: bytes) -> None: ...

    def close(self) -> None: ...


class Buffer:
    """A small text field kept in memory, up to `cap` bytes (413 naming it past that)."""

    def __init__(self, name: str, cap: int, done: Callable[[bytes], None]):
        self.name, self.cap, self.done, self.data = name, cap, done, bytearray()

    def write(self, chunk: bytes) -> None:
        self.data += chunk
        if len(self.data) > self.cap:
            raise ServiceError(413, "payload_too_large", f"the '{self.name}' field exceeds {self.cap} bytes", self.name)

    def close(self) -> None:
        self.done(bytes(self.data))


class DiskRoom:
    """The room an upload may take on the data directory's disk: its free bytes, measured when
    the upload starts, less what is kept free (PHD_KEEP_FREE_BYTES). Past it: 507."""

    def __init__(self, folder: Path, keep_free: int):
        self.free, self.keep_free = shutil.disk_usage(folder).free, keep_free

    def check(self, size: int | str, what: str, field: str) -> None:
        """507 naming `field` when `size` bytes (a Content-Length header's text: when it is a number) do not fit."""
        if isinstance(size, str):
            if not size.isdigit():
                return
            size = int(size)
        if size > self.free - self.keep_free:
            kept = f", of which {self.keep_free} are kept free (PHD_KEEP_FREE_BYTES)" if self.keep_free else ""
            raise insufficient_storage(f"{what} ({size} bytes)", field,
                                       f"the service's disk has {self.free} bytes free{kept}")


@dataclass
class _State:
    headers: dict[str, str] = field(default_factory=dict)
    header_name: bytes = b""
    header_value: bytes = b""
    name: str = ""
    sink: Sink | None = None


def boundary(request: Request, message: str, field: str) -> bytes:
    """The body's multipart boundary; 415 with `message` (what to send) for any other body."""
    content_type, params = parse_options_header(request.headers.get("content-type", ""))
    if content_type != b"multipart/form-data" or not params.get(b"boundary"):
        raise ServiceError(415, "unsupported_media_type", message, field)
    return params[b"boundary"]


class FileSink:
    """A part written to a file as it arrives; `count(n)` is told each chunk's size first (it
    raises past a cap or past the disk's room), `seen(chunk)` may look at the bytes (a hash)."""

    def __init__(self, path: Path, count: Callable[[int], None], seen: Callable[[bytes], None] | None = None,
                 mode: str = "wb"):
        self.file = open(path, mode)
        self.count, self.seen = count, seen

    def write(self, chunk: bytes) -> None:
        self.count(len(chunk))
        if self.seen is not None:
            self.seen(chunk)
        self.file.write(chunk)

    def close(self) -> None:
        self.file.close()


async def read_parts(request: Request, separator: bytes, open_part: Callable[[Part], Sink], *, what: str,
                     field: str) -> None:
    """Stream the body through the parser; `open_part(part)` is asked, once a part's headers are
    in, for the sink of its bytes (it raises to refuse the part). A full disk while writing is
    507 naming `what` and `field`."""
    state = _State()

    def on_part_begin() -> None:
        nonlocal state
        state = _State()

    def on_header_field(data: bytes, start: int, end: int) -> None:
        state.header_name += data[start:end]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        state.header_value += data[start:end]

    def on_header_end() -> None:
        state.headers[state.header_name.decode("latin-1").lower()] = state.header_value.decode("latin-1")
        state.header_name, state.header_value = b"", b""

    def on_headers_finished() -> None:
        _, options = parse_options_header(state.headers.get("content-disposition", ""))
        state.name = options.get(b"name", b"").decode("utf-8", "replace")
        raw_filename = options.get(b"filename")
        state.sink = open_part(Part(state.name, None if raw_filename is None else
                                    raw_filename.decode("utf-8", "replace")))

    def on_part_data(data: bytes, start: int, end: int) -> None:
        assert state.sink is not None           # on_headers_finished opened it
        state.sink.write(data[start:end])

    def on_part_end() -> None:
        nonlocal state
        if state.sink is not None:              # None: its headers never finished, no named field
            sink, state.sink = state.sink, None
            sink.close()
        state = _State()                        # an error between parts is no part's (names `field`)

    try:
        parser = MultipartParser(separator, {
            "on_part_begin": on_part_begin, "on_header_field": on_header_field, "on_header_value": on_header_value,
            "on_header_end": on_header_end, "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data, "on_part_end": on_part_end,
        })
    except FormParserError as exc:      # e.g. a boundary past the parser's 256 characters
        raise ServiceError(400, "invalid_multipart", f"the multipart boundary is refused: {exc}",
                           "Content-Type") from None
    try:
        with writing(what, field):
            async for chunk in request.stream():
                parser.write(chunk)
            parser.finalize()
    except ClientDisconnect:
        raise ServiceError(400, "upload_incomplete", "the upload ended before the body was complete", field) from None
    except FormParserError as exc:
        raise ServiceError(400, "invalid_multipart", f"malformed multipart body: {exc}", state.name or field) from None
    finally:
        if isinstance(state.sink, FileSink):     # a part cut off mid-way: its file is closed (the caller removes it)
            with writing(what, field):
                state.sink.close()
