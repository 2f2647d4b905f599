"""A cap on request bodies outside the upload endpoint, enforced before anything parses them.

A JSON body is parsed on the event loop: without a cap a 200 MB body grew the API process by 800 MB and stalled
every other request. Bodies over ``limit`` are answered 413 naming the limit: at once when ``Content-Length``
says so, or as soon as a chunked body passes the limit. The tus endpoint (``/v1/uploads``) streams to disk with
its own limits and is not capped here.
"""

from __future__ import annotations

import json

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

UNCAPPED_PREFIX = "/v1/uploads"


class BodyTooLarge(HTTPException):
    """Raised inside ``receive`` when a streamed body passes the limit; an HTTPException, so that FastAPI's body
    parsing passes it on and the app's handler answers it as JSON."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, detail=limit_message(limit))


def limit_message(limit: int) -> str:
    """The 413 message, naming the limit and its setting."""
    return (
        f"request body over the limit of {limit} bytes (PANOGS_MAX_JSON_BODY_BYTES); upload bundles through /v1/uploads"
    )


class BodyLimit:
    """Pure ASGI middleware (no buffering of its own)."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    def _message(self) -> bytes:
        return json.dumps({"type": "payload_too_large", "message": limit_message(self.limit)}).encode()

    async def _refuse(self, send: Send) -> None:
        body = self._message()
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await send({"type": "http.response.start", "status": 413, "headers": [*headers, (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"].startswith(UNCAPPED_PREFIX):
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.strip().isdigit() and int(declared) > self.limit:
            await self._refuse(send)
            return
        received = 0
        started = False

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise BodyTooLarge(self.limit)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, tracking_send)
        except BodyTooLarge:
            if not started:
                await self._refuse(send)
