"""Service errors: each carries its HTTP status and a stable ``type``; one handler turns them into JSON.

Every error response is ``{"type": ..., "message": ...}`` (plus ``problems`` where there are several).
No stack trace leaves the server: unexpected exceptions are logged with their traceback and a request id and
answered with a 500 that names only that id.

Database errors are answered by what they mean (``service.db.faults``): an integrity error is the client's
conflict (409) or a refused value (422), an outage is a 503 with ``Retry-After``, and anything else is a bug
(500, logged with its traceback), never a retryable 503 that hides it.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.db.faults import DatabaseFault, classify

logger = logging.getLogger(__name__)


class ServiceError(Exception):
    """Base of the errors the API answers on purpose."""

    status_code = 400
    type = "bad_request"

    def __init__(
        self, message: str, *, problems: list[str] | None = None, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(message)
        self.message = message
        self.problems = problems
        self.headers = headers

    def body(self) -> dict[str, Any]:
        """The JSON body of the response."""
        out: dict[str, Any] = {"type": self.type, "message": self.message}
        if self.problems is not None:
            out["problems"] = self.problems
        return out


class Unauthorized(ServiceError):
    """Missing, malformed, unknown or revoked API key."""

    status_code = 401
    type = "unauthorized"

    def __init__(self, message: str) -> None:
        super().__init__(message, headers={"WWW-Authenticate": "Bearer"})


class NotFound(ServiceError):
    """The resource does not exist, or belongs to another tenant (indistinguishable on purpose)."""

    status_code = 404
    type = "not_found"

    def __init__(self, kind: str, ident: object) -> None:
        super().__init__(f"{kind} {ident} not found")


class Conflict(ServiceError):
    """The resource is not in a state that allows the request."""

    status_code = 409
    type = "conflict"


class InvalidInput(ServiceError):
    """The request is well-formed but its content is refused."""

    status_code = 422
    type = "invalid_input"


class InvalidBundle(InvalidInput):
    """The uploaded bundle breaks docs/scene_format.md; ``problems`` lists every problem found."""

    type = "invalid_bundle"


class PayloadTooLarge(ServiceError):
    """More bytes than the limit allows."""

    status_code = 413
    type = "payload_too_large"


class UnsupportedMediaType(ServiceError):
    """Wrong Content-Type for the endpoint."""

    status_code = 415
    type = "unsupported_media_type"


class ChecksumMismatch(ServiceError):
    """The bytes do not match the checksum given (tus checksum extension status 460)."""

    status_code = 460
    type = "checksum_mismatch"


class PreconditionFailed(ServiceError):
    """A protocol header is missing or unsupported (e.g. Tus-Resumable)."""

    status_code = 412
    type = "precondition_failed"


class Forbidden(ServiceError):
    """Authenticated, but this request is not allowed as sent."""

    status_code = 403
    type = "forbidden"


class QuotaExceeded(ServiceError):
    """A per-tenant limit (stored bytes: 413; concurrent jobs: 429); the message names the limit."""

    type = "quota_exceeded"

    def __init__(self, message: str, *, status_code: int) -> None:
        super().__init__(message)
        self.status_code = status_code


class ServiceUnavailable(ServiceError):
    """A dependency (database, broker, encoder) cannot be reached right now."""

    status_code = 503
    type = "service_unavailable"


_STATUS_TYPES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    416: "range_not_satisfiable",
    422: "invalid_input",
}


# What the client is told for each database fault that is not a bug: (status, type, message).
_FAULT_ANSWERS = {
    DatabaseFault.DUPLICATE: (409, "conflict", "the request conflicts with data that already exists"),
    DatabaseFault.MISSING_REFERENCE: (409, "conflict", "the request refers to something that no longer exists"),
    DatabaseFault.CONSTRAINT: (422, "invalid_input", "a value of the request is refused by the database"),
    DatabaseFault.OUTAGE: (503, "service_unavailable", "the database is unavailable; retry shortly"),
}
RETRY_AFTER_S = 2  # a database outage: when the client should try again


def _format_location(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc if p not in ("body",)]
    return ".".join(parts) or "body"


def install_error_handlers(app: FastAPI) -> None:
    """Register the one JSON error format for every error the app can answer."""

    @app.exception_handler(ServiceError)
    async def _service_error(_request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse(exc.body(), status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse(validation_body(exc.errors(), app.state.settings.max_validation_problems), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_request: Request, exc: StarletteHTTPException) -> JSONResponse:
        body = {"type": _STATUS_TYPES.get(exc.status_code, "error"), "message": str(exc.detail)}
        return JSONResponse(body, status_code=exc.status_code, headers=getattr(exc, "headers", None))

    @app.exception_handler(DBAPIError)
    @app.exception_handler(PoolTimeoutError)
    async def _database_error(request: Request, exc: DBAPIError | PoolTimeoutError) -> JSONResponse:
        return database_error_response(request, exc)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        return internal_error_response(request, exc)


def validation_body(errors: Sequence[Any], limit: int) -> dict[str, Any]:
    """A 422 body with the first ``limit`` problems and a count of the rest: a body with a million bad keys must
    not come back as a megabyte of errors. Values are not echoed, only where and what."""
    problems = [f"{_format_location(tuple(e.get('loc', ())))}: {e.get('msg', 'invalid')}"[:300] for e in errors[:limit]]
    if len(errors) > limit:
        problems.append(f"... and {len(errors) - limit} more problem(s)")
    return {
        "type": "invalid_input",
        "message": f"the request is not valid ({len(errors)} problem(s))",
        "problems": problems,
    }


def database_error_response(request: Request, exc: DBAPIError | PoolTimeoutError) -> JSONResponse:
    """The answer to a database error, by its :class:`DatabaseFault`; a bug goes to the server log in full."""
    fault = classify(exc)
    if fault is DatabaseFault.BUG:
        return internal_error_response(request, exc)
    status, kind, message = _FAULT_ANSWERS[fault]
    # Expected faults need no traceback: the fault and the driver's error class say what happened.
    cause = type(exc.orig).__name__ if isinstance(exc, DBAPIError) else type(exc).__name__
    logger.warning("database %s on %s %s: %s", fault.value, request.method, request.url.path, cause)
    headers = {"Retry-After": str(RETRY_AFTER_S)} if fault is DatabaseFault.OUTAGE else None
    return JSONResponse({"type": kind, "message": message}, status_code=status, headers=headers)


def internal_error_response(request: Request, exc: BaseException) -> JSONResponse:
    """A 500 naming a request id; the traceback goes to the server log under that id, never to the client."""
    request_id = uuid.uuid4().hex[:12]
    logger.error("unhandled error on %s %s (request %s)", request.method, request.url.path, request_id, exc_info=exc)
    body = {"type": "internal_error", "message": f"internal error (request {request_id}); see the server log"}
    return JSONResponse(body, status_code=500)
