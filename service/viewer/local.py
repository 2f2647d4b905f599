"""``panogs view RUN_DIR``: the viewer for one finished run folder, served on 127.0.0.1 by the standard library.

Routes: ``/`` the viewer page, ``/static/...`` the built assets, ``/scene.bin`` the binary scene (built once at
start), ``/gaussians.ply`` the run's Gaussian scene for the photo view (key ``p``), ``/cameras.json`` the capture
frames' poses (the viewer's "look from" list), ``POST /query`` the same query code as the API's
``/v1/jobs/{id}/query``.
"""

from __future__ import annotations

import json
import logging
import mimetypes
import sys
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from panogs_core.bounded_json import JsonLimitError, JsonSyntaxError, loads
from service.viewer.assets import static_dir
from service.viewer.scene import build_scene

logger = logging.getLogger("panogs.view")
MAX_QUERY_BODY = 64 * 1024  # a query body is a short JSON object; anything longer is refused unread


class RunViewer:
    """A finished run, ready to serve: its encoded scene and its loaded result for queries."""

    def __init__(self, run_dir: Path, encoder: Any = None) -> None:
        from panogs_core.io.run_folder import load_result

        self.run_dir = run_dir
        self.scene = build_scene(run_dir, extra={"title": run_dir.resolve().name})
        self.result = load_result(run_dir)
        self.encoder = encoder
        self.static = static_dir()
        self._lock = threading.Lock()  # one query at a time through the encoder child

    def query(self, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        """(status, JSON) of a query, as the API answers it."""
        from service.errors import ServiceError
        from service.job_results import run_query
        from service.schemas import QueryCreate

        try:
            parsed = QueryCreate.model_validate(body)
        except ValidationError as exc:
            problems = [f"{'.'.join(str(p) for p in e['loc']) or 'body'}: {e['msg']}" for e in exc.errors()[:5]]
            return 422, {"type": "invalid_input", "message": "the request is not valid", "problems": problems}
        try:
            with self._lock:
                answer = run_query(self.result, parsed, self.encoder)
        except ServiceError as exc:
            return exc.status_code, exc.body()
        return 200, answer.model_dump(mode="json")


def make_handler(run: RunViewer) -> type[BaseHTTPRequestHandler]:
    """The request handler class bound to ``run``."""

    class Handler(BaseHTTPRequestHandler):
        server_version = "panogs-view"

        def log_message(self, format: str, *args: Any) -> None:
            logger.debug(format, *args)

        def _send(self, status: int, body: bytes, content_type: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-cache")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, status: int, doc: dict[str, Any]) -> None:
            self._send(status, json.dumps(doc).encode(), "application/json")

        def do_GET(self) -> None:
            path = self.path.split("?")[0].split("#")[0]
            if path in ("/", "/index.html"):
                return self._file(run.static / "viewer.html")
            if path == "/scene.bin":
                return self._send(200, run.scene.data, "application/octet-stream")
            for name in ("gaussians.ply", "cameras.json"):
                if path == f"/{name}" and (run.run_dir / name).is_file():
                    return self._file(run.run_dir / name)
            if path.startswith("/static/"):
                name = path.removeprefix("/static/")
                if "/" not in name and (run.static / name).is_file():
                    return self._file(run.static / name)
            self._json(404, {"type": "not_found", "message": f"no such page: {path}"})

        def _file(self, path: Path) -> None:
            kind = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
            self._send(200, path.read_bytes(), kind)

        def do_POST(self) -> None:
            if self.path != "/query":
                return self._json(404, {"type": "not_found", "message": f"no such endpoint: {self.path}"})
            length = int(self.headers.get("Content-Length") or 0)
            if length > MAX_QUERY_BODY:
                return self._json(413, {"type": "payload_too_large", "message": f"body over {MAX_QUERY_BODY} bytes"})
            try:
                body = loads(self.rfile.read(length) or b"{}", source="request body")
            except JsonLimitError as exc:  # nested too deep or a huge integer: the one bounded reader's answer
                return self._json(422, {"type": "invalid_input", "message": str(exc)})
            except JsonSyntaxError as exc:
                return self._json(400, {"type": "bad_request", "message": f"body is not JSON ({exc})"})
            if not isinstance(body, dict):
                return self._json(422, {"type": "invalid_input", "message": "body must be a JSON object"})
            self._json(*run.query(body))

    return Handler


# A tab closed, reloaded or moved on while its answer was being written: nothing went wrong on this side.
GONE = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError)


class ViewerServer(ThreadingHTTPServer):
    """The standard library's threading server, quiet about browsers that leave before their answer is written."""

    daemon_threads = True

    def handle_error(self, request: Any, client_address: Any) -> None:
        if isinstance(sys.exc_info()[1], GONE):
            logger.debug("%s left before its answer was written", client_address)
            return
        super().handle_error(request, client_address)


def make_server(run: RunViewer, port: int) -> ViewerServer:
    """The server of ``run`` on 127.0.0.1 (port 0: any free port), listening, not yet serving."""
    return ViewerServer(("127.0.0.1", port), make_handler(run))


def serve(run: RunViewer, port: int, on_ready: Callable[[str], None]) -> None:
    """Serve until interrupted; ``on_ready(url)`` once the socket listens (port 0: any free port)."""
    server = make_server(run, port)
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    on_ready(url)
    try:
        server.serve_forever()
    finally:
        server.server_close()
