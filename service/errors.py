"""The service's errors: one exception type that knows its HTTP status, code and field.

Every error answer has the body `{"error": {"code", "message", "field"}}`
(`service.schemas.ErrorResponse`). Library errors map onto it in one place,
`from_exception`: `InputError` -> 422 naming its field (413 for `TooLarge`), unknown model
content -> 415.
"""

from __future__ import annotations

import json

from phd_core.errors import InputError, TooLarge, cut
from phd_core.executors import ExecutorError
from phd_core.uq import CalibrationError

from .schemas import ErrorDetail

# What json.loads raises on text that is not JSON it can decode: bad syntax, bytes that are not
# UTF-8/16/32, and arrays or objects nested past the interpreter's recursion limit (about 1,000).
JSON_ERRORS = (json.JSONDecodeError, UnicodeDecodeError, RecursionError)
MESSAGE_CHARS = 2000        # an error answer's message at most
FIELD_CHARS = 200           # ... and the field it names


def error_detail(code: str, message: str, field: str | None = None) -> ErrorDetail:
    """The `error` of every error answer and of every failed job; the message and the field cut to
    MESSAGE_CHARS and FIELD_CHARS (they may quote a user's file or request)."""
    return ErrorDetail(code=code, message=cut(message, MESSAGE_CHARS), field=None if field is None else
                       cut(field, FIELD_CHARS))


def error_body(code: str, message: str, field: str | None = None) -> bytes:
    """The body of every error answer, from the routes, the guard and the HTTP protocol alike."""
    return json.dumps({"error": error_detail(code, message, field).model_dump()}).encode()


def json_problem(exc: BaseException | None) -> str | None:
    """Why json.loads refused a text, in the client's words; None if `exc` is not such a refusal."""
    if isinstance(exc, RecursionError):
        return "nested too deeply (arrays and objects may nest about 1,000 levels)"
    return str(exc) if isinstance(exc, JSON_ERRORS) else None


class ServiceError(Exception):
    """An error answer: HTTP status, stable code, message and the offending field."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None,
                 headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.headers = headers or {}

    def detail(self) -> ErrorDetail:
        return error_detail(self.code, self.message, self.field)


def not_found(what: str, ident: str, field: str | None = None) -> ServiceError:
    return ServiceError(404, f"{what}_not_found", f"no {what} with id '{ident}'", field)


def invalid(field: str | None, message: str) -> ServiceError:
    return ServiceError(422, "invalid_input", message, field)


def busy(field: str | None, retry_after: int) -> ServiceError:
    """429: the memory budget stayed taken by other work for as long as a request may wait."""
    return ServiceError(429, "busy", "the service's memory budget is taken by other work; retry later", field,
                        {"Retry-After": str(retry_after)})


def insufficient_storage(what: str, field: str | None = None, why: str = "the service's disk is full") -> ServiceError:
    """507: the data directory's disk (or quota) is full, or the write would eat into the space kept
    free (`why`); `what` names what could not be written. Nothing of it was kept
    (service.store.writing), and what was stored before is unchanged."""
    return ServiceError(507, "insufficient_storage", f"{why}: {what} could not be written (nothing of it was kept; "
                        "what was stored before is unchanged); retry once space is freed", field)


def from_exception(exc: BaseException) -> ServiceError | None:
    """The error answer for a library exception, or None if it is a bug (-> 500)."""
    if isinstance(exc, ServiceError):
        return exc
    if isinstance(exc, InputError):
        from phd_core.renderers import UnknownModelError  # the library's content sniffer

        if isinstance(exc, UnknownModelError):
            return ServiceError(415, "unsupported_model", exc.reason, exc.field)
        if isinstance(exc, TooLarge):
            return ServiceError(413, "payload_too_large", exc.reason, exc.field)
        code = "calibration_failed" if isinstance(exc, CalibrationError) else "invalid_input"
        return ServiceError(422, code, exc.reason, exc.field)
    if isinstance(exc, ExecutorError):     # the compute cluster failed, not the request
        return ServiceError(503, "executor_failed", str(exc))
    return None
