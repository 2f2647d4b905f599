"""Security headers on every response of the service: API, app pages, assets, errors and 404s.

No page may be framed (``X-Frame-Options: DENY`` and CSP ``frame-ancestors 'none'``: no clickjacking of the app),
no response is content-sniffed (``nosniff``: a JSON or PNG answer is never run as a script) and no URL leaves in a
``Referer`` (``no-referrer``: job ids in the app's URL stay on the page). The Content-Security-Policy depends on
what the response is:

- the app's pages (``/app``) load only the service's own scripts and styles (the built bundles hold no inline
  code), draw WebGL on a canvas, read images from ``data:``/``blob:`` URLs and talk to this origin only;
- the OpenAPI pages (``/docs``, ``/redoc``) are FastAPI's: Swagger UI and ReDoc load from the jsDelivr CDN and
  start with an inline script, so they get exactly that and nothing more;
- everything else (JSON, PNG, PLY, assets) may load nothing at all (``default-src 'none'``).

A header a route set itself is kept. The 500 answer of an unexpected exception is written outside every
middleware (Starlette's ``ServerErrorMiddleware``), so :func:`service.errors.internal_error_response` adds
:data:`API_HEADERS` itself.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

_COMMON = {
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}
API_CSP = "default-src 'none'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
# 'wasm-unsafe-eval': the viewer's photo view (Spark, web/src/viewer/photo.js) compiles its WebAssembly module, the
# splat sorter and PLY decoder, from bytes in its own bundle; it allows compiling WebAssembly only, not eval() or
# new Function(), and no other origin. Its worker is a blob: URL of the same bundle (worker-src, already there).
APP_CSP = (
    "default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; style-src 'self'; img-src 'self' data: blob:; "
    "connect-src 'self'; "
    "worker-src 'self' blob:; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
_CDN = "https://cdn.jsdelivr.net"
DOCS_CSP = (
    f"default-src 'self'; script-src 'self' 'unsafe-inline' {_CDN}; "
    f"style-src 'self' 'unsafe-inline' {_CDN} https://fonts.googleapis.com; font-src 'self' https://fonts.gstatic.com; "
    f"img-src 'self' data: {_CDN} https://fastapi.tiangolo.com; connect-src 'self'; worker-src 'self' blob:; "
    "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
API_HEADERS = {**_COMMON, "Content-Security-Policy": API_CSP}
APP_PAGES = ("/app", "/app/")
DOCS_PAGES = ("/docs", "/docs/oauth2-redirect", "/redoc")


def headers_for(path: str) -> dict[str, str]:
    """The security headers of a response to ``path``."""
    if path in APP_PAGES:
        csp = APP_CSP
    elif path in DOCS_PAGES:
        csp = DOCS_CSP
    else:
        csp = API_CSP
    return {**_COMMON, "Content-Security-Policy": csp}


class SecurityHeaders:
    """ASGI middleware: add :func:`headers_for` to every HTTP response that does not set them already."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = [(k.lower().encode(), v.encode()) for k, v in headers_for(scope.get("path", "")).items()]

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []), *(h for h in extra if h[0] not in present)]
            await send(message)

        await self.app(scope, receive, with_headers)
