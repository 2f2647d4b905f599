"""JSON request bodies pass the bounded reader before FastAPI parses them.

FastAPI parses a JSON body with ``json.loads`` and validates it with pydantic, neither of which has limits: a
``config`` nested 300 levels deep in a 2 KB body passed both and broke pydantic's serializer (a 500), and
1,000 levels break the parser itself. This middleware checks every request body with
:func:`panogs_core.bounded_json.loads` and answers a broken limit with 422 ``invalid_input`` naming the field,
the limit and its setting. Bodies within the limits go on unchanged; a syntax error (a body that is not JSON at
all) is left to the route, and FastAPI's own 422 says where.

Every body is checked, whatever its ``Content-Type`` says: deciding "is this JSON?" a second time, beside the
framework, is what let bodies through before (two ``Content-Type`` headers, of which this module read the last and
FastAPI the first; a trailing byte that ``bytes.strip`` keeps and ``str.strip`` removes). Every route but the
upload endpoint takes JSON, so a body that breaks a JSON limit is refused on any of them. It sits inside
:class:`service.body_limit.BodyLimit`, so it never buffers more than that cap. The tus endpoint (``/v1/uploads``)
carries bytes, not JSON, and is not read here.
"""

from __future__ import annotations

import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from panogs_core.bounded_json import JsonLimitError, JsonLimits, JsonSyntaxError, loads
from service.body_limit import UNCAPPED_PREFIX
from service.settings import Settings

# The setting behind each limit, for the messages.
LIMIT_SETTINGS = {
    "depth": "PANOGS_MAX_JSON_DEPTH",
    "int_digits": "PANOGS_MAX_JSON_INT_DIGITS",
    "bytes": "PANOGS_MAX_JSON_BODY_BYTES",
}


def body_limits(settings: Settings) -> JsonLimits:
    """The limits of a request body, from the settings."""
    return JsonLimits(
        max_depth=settings.max_json_depth,
        max_bytes=settings.max_json_body_bytes,
        max_int_digits=settings.max_json_int_digits,
    )


class BoundedJsonBody:
    """Pure ASGI middleware: buffers a JSON body (already capped by ``BodyLimit``), checks it, replays it."""

    def __init__(self, app: ASGIApp, limits: JsonLimits) -> None:
        self.app = app
        self.limits = limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"].startswith(UNCAPPED_PREFIX):
            await self.app(scope, receive, send)
            return
        chunks: list[bytes] = []
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return  # the client left before sending its body: nobody to answer
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body:
            try:
                loads(body, self.limits, source="request body")
            except JsonLimitError as exc:
                await _refuse(send, exc)
                return
            except JsonSyntaxError:
                pass  # within the limits, so FastAPI's parser is safe on it; its 422 names the position
        await self.app(scope, _replay(body, receive), send)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that hands the app the buffered body once, then waits on the client (for a disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def _refuse(send: Send, exc: JsonLimitError) -> None:
    setting = LIMIT_SETTINGS[exc.limit]
    message = f"the request body breaks a JSON limit (set by {setting}); nothing was done"
    body = json.dumps({"type": "invalid_input", "message": message, "problems": [str(exc)]}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": 422, "headers": headers})
    await send({"type": "http.response.body", "body": body})
