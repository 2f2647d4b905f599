"""Service errors: each carries its HTTP status and a stable ``type``; one handler turns them into JSON.

Every error response is ``{"type": ..., "message": ...}`` (plus ``problems`` where there are several).
No stack trace leaves the server: unexpected exceptions are logged with their traceback and a request id and
answered with a 500 that names only that id. Every error body, whichever handler writes it, goes through
:func:`sanitize_message` on the way out: a path under the storage folder is cut to its part below it
(``scenes/<id>/bundle/frames/0001.png``), any other absolute path becomes ``<path>``, and a message that holds a
Python traceback is replaced by one naming a request id; the original is logged under that id.

Database errors are answered by what they mean (``service.db.faults``): an integrity error is the client's
conflict (409) or a refused value (422), an outage is a 503 with ``Retry-After``, and anything else is a bug
(500, logged with its traceback), never a retryable 503 that hides it.
"""

from __future__ import annotations

import logging
import re
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.db.faults import DatabaseFault, classify
from service.security_headers import API_HEADERS
from service.storage.objects import StorageUnavailable

logger = logging.getLogger(__name__)
STORAGE_RETRY_AFTER_S = 5  # a storage outage: when the client should try again (/readyz re-probes as often)
STORAGE_OUTAGE_MESSAGE = "the object storage is unavailable; retry shortly (GET /readyz says when it is back)"


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


class FitNotReady(Conflict):
    """The job's results are ready but its Gaussian scene is not (its fit runs, failed or was canceled).

    The body adds ``fit``: ``{"state", "progress", "error"}``; while the fit runs, ``Retry-After`` says when to ask
    again.
    """

    type = "fit_not_ready"

    def __init__(self, message: str, fit: dict[str, Any], *, retry_after_s: int | None = None) -> None:
        headers = {"Retry-After": str(retry_after_s)} if retry_after_s is not None else None
        super().__init__(message, headers=headers)
        self.fit = fit

    def body(self) -> dict[str, Any]:
        return {**super().body(), "fit": self.fit}


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


class InsufficientStorage(ServiceError):
    """The storage volume has not the room a request needs (keeping ``min_free_disk_bytes`` free)."""

    status_code = 507
    type = "insufficient_storage"


class StorageOutage(ServiceError):
    """The object storage did not answer (or answered that it is busy): the request may succeed once it is back."""

    status_code = 503
    type = "storage_unavailable"

    def __init__(self, message: str = STORAGE_OUTAGE_MESSAGE) -> None:
        super().__init__(message, headers={"Retry-After": str(STORAGE_RETRY_AFTER_S)})


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


class TooManyRequests(ServiceError):
    """A per-tenant limit on work in flight (renders); ``Retry-After`` says when to try again."""

    status_code = 429
    type = "too_many_requests"

    def __init__(self, message: str, *, retry_after_s: int) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


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


# An absolute POSIX path of two segments or more, not inside a word, a URL or a relative path ("a/b", "x://h/p").
_ABSOLUTE_PATH = re.compile(r"(?<![\w.:/~-])/[\w.+@~-]+(?:/[\w.+@~-]*)+")
_API_PATHS = ("/v1/", "/app/", "/docs/", "/healthz", "/readyz")  # the service's own routes are not host paths
_TRACEBACK = re.compile(r"Traceback \(most recent call last\)|File \"[^\"]*\", line \d+")
REDACTED_PATH = "<path>"


def sanitize_message(text: str, roots: Sequence[Path] = ()) -> str:
    """``text`` without host paths: below one of ``roots`` a path is shown relative to it, any other becomes
    ``<path>``. The service's own URL paths (``/v1/...``) stay."""
    prefixes = sorted((str(Path(r)).rstrip("/") + "/" for r in roots), key=len, reverse=True)

    def replace(match: re.Match[str]) -> str:
        found = match.group(0)
        if found.startswith(_API_PATHS):
            return found
        for prefix in prefixes:
            if found.startswith(prefix) and len(found) > len(prefix):
                return found[len(prefix) :]
        return REDACTED_PATH

    return _ABSOLUTE_PATH.sub(replace, text)


def has_traceback(text: str) -> bool:
    """Whether ``text`` holds (part of) a Python traceback."""
    return _TRACEBACK.search(text) is not None


def _storage_roots(request: Request) -> list[Path]:
    """The folders whose paths a message may name relative to them: the storage folder, then the data folder."""
    roots: list[Path] = []
    storage = getattr(request.app.state, "storage", None)
    if storage is not None:
        roots.append(storage.root)
    settings = getattr(request.app.state, "settings", None)
    if settings is not None:
        roots += [settings.storage, Path(settings.data_dir).resolve()]
    return roots


def safe_error_body(request: Request, body: dict[str, Any]) -> dict[str, Any]:
    """The body of an error response as it may leave the server (module docstring); logs what it changed."""
    fit = body.get("fit") if isinstance(body.get("fit"), dict) else None
    texts = [body.get("message", ""), *(body.get("problems") or []), (fit or {}).get("error") or ""]
    if any(isinstance(t, str) and has_traceback(t) for t in texts):
        request_id = uuid.uuid4().hex[:12]
        logger.error("a traceback was about to be answered on %s %s (request %s): %r", request.method,
                     request.url.path, request_id, body)  # fmt: skip
        return {
            "type": body.get("type", "error"),
            "message": f"internal error (request {request_id}); see the server log",
        }
    roots = _storage_roots(request)
    out = dict(body)
    if isinstance(body.get("message"), str):
        out["message"] = sanitize_message(body["message"], roots)
    if isinstance(body.get("problems"), list):
        out["problems"] = [sanitize_message(p, roots) if isinstance(p, str) else p for p in body["problems"]]
    if fit is not None and isinstance(fit.get("error"), str):
        out["fit"] = {**fit, "error": sanitize_message(fit["error"], roots)}
    if out != body:
        logger.info("host paths cut from the error answered on %s %s: %r", request.method, request.url.path, body)
    return out


def error_response(
    request: Request, body: dict[str, Any], status_code: int, headers: dict[str, str] | None = None
) -> JSONResponse:
    """The one way an error leaves the server: a sanitised JSON body (:func:`safe_error_body`)."""
    return JSONResponse(safe_error_body(request, body), status_code=status_code, headers=headers)


def _format_location(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc if p not in ("body",)]
    return ".".join(parts) or "body"


def allowed_methods(request: Request) -> list[str] | None:
    """Every method the API documents at this request's path, or None for a path outside the OpenAPI schema.

    Starlette answers a 405 from the first route whose path matches, naming only that route's methods: ``PUT
    /v1/jobs`` said ``Allow: POST`` though ``GET /v1/jobs`` exists too. The schema lists every operation of a
    path together, so it is the one place that knows them all.
    """
    path = request.url.path
    for template, operations in request.app.openapi().get("paths", {}).items():
        pattern = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(template))
        if re.fullmatch(pattern, path):
            return sorted(method.upper() for method in operations if method.upper() in _HTTP_METHODS)
    return None


_HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


def install_error_handlers(app: FastAPI) -> None:
    """Register the one JSON error format for every error the app can answer."""

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return error_response(request, exc.body(), exc.status_code, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        return error_response(request, validation_body(exc.errors(), app.state.settings.max_validation_problems), 422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        body = {"type": _STATUS_TYPES.get(exc.status_code, "error"), "message": str(exc.detail)}
        headers = getattr(exc, "headers", None)
        methods = allowed_methods(request) if exc.status_code == 405 else None
        if methods:  # with the matched route's own, which may be outside the schema (tus's OPTIONS)
            own = (headers or {}).get("Allow", "")
            every = sorted({*methods, *(m.strip() for m in own.split(",") if m.strip())})
            headers = {**(headers or {}), "Allow": ", ".join(every)}
        return error_response(request, body, exc.status_code, headers)

    @app.exception_handler(DBAPIError)
    @app.exception_handler(PoolTimeoutError)
    async def _database_error(request: Request, exc: DBAPIError | PoolTimeoutError) -> JSONResponse:
        return database_error_response(request, exc)

    @app.exception_handler(StorageUnavailable)
    async def _storage_outage(request: Request, exc: StorageUnavailable) -> JSONResponse:
        # What the store said stays in the log: its host and bucket are the operator's, not the client's.
        logger.warning("storage unavailable on %s %s: %s", request.method, request.url.path, exc)
        outage = StorageOutage()
        return error_response(request, outage.body(), outage.status_code, outage.headers)

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
    return error_response(request, {"type": kind, "message": message}, status, headers)


def internal_error_response(request: Request, exc: BaseException) -> JSONResponse:
    """A 500 naming a request id; the traceback goes to the server log under that id, never to the client."""
    request_id = uuid.uuid4().hex[:12]
    logger.error("unhandled error on %s %s (request %s)", request.method, request.url.path, request_id, exc_info=exc)
    body = {"type": "internal_error", "message": f"internal error (request {request_id}); see the server log"}
    # Answered by Starlette's outermost middleware, past the security headers' one: they are added here.
    return JSONResponse(body, status_code=500, headers=API_HEADERS)
