"""``panogs export-html RUN_DIR OUT.html``: one self-contained file that opens offline (data, code and style inline).

Above ``max_primitives`` the scene is decimated (a seeded random subset, said in the viewer's summary); a file
that would still exceed ``max_bytes`` is refused with a message naming both limits. Class-name queries work
offline: the file carries each vocabulary class's answer, computed by the API's query code, and the capture frames'
poses (``cameras.json``) for the viewer's "look from" list.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import Any

from panogs_core.errors import InputError
from service.viewer.assets import static_dir

DEFAULT_MAX_PRIMITIVES = 1_000_000  # decimate above this
DEFAULT_MAX_BYTES = 64 * 1024 * 1024  # refuse a file larger than this (mail and browsers choke on more)


def class_queries(run_dir: Path) -> dict[str, Any]:
    """The answer of the query endpoint to each class name of the run's vocabulary (default top-k)."""
    from panogs_core.io.run_folder import load_result
    from service.job_results import run_query
    from service.schemas import QueryCreate

    result = load_result(run_dir)
    answers: dict[str, Any] = {}
    for name in result.vocabulary.names:
        answer = run_query(result, QueryCreate(text=name), None)
        answers[name.lower()] = answer.model_dump(mode="json")
    return answers


def capture_frames(run_dir: Path) -> dict[str, Any]:
    """``{"cameras": cameras.json}`` for the viewer's "look from" list, or nothing when the run has none."""
    from panogs_core.io.run_folder import CAMERAS_JSON
    from panogs_core.io.run_json import read_run_json

    path = CAMERAS_JSON.path(run_dir)
    return {"cameras": read_run_json(path)} if path.is_file() else {}


def export_html(
    run_dir: str | Path,
    out: str | Path,
    *,
    max_primitives: int = DEFAULT_MAX_PRIMITIVES,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> dict[str, int]:
    """Write the offline viewer of ``run_dir`` to ``out``; returns primitives kept, primitives in the run, bytes.

    Raises:
        InputError: the run folder is incomplete, or the file would exceed ``max_bytes``.
    """
    from service.viewer.scene import build_scene  # numpy: not at import (the panogs CLI's parser imports this)

    run = Path(run_dir)
    extra = {"title": run.resolve().name, "class_queries": class_queries(run), **capture_frames(run)}
    scene = build_scene(run, max_primitives=max_primitives, extra=extra)
    assets = static_dir()
    script = (assets / "viewer.js").read_text().replace("</script", "<\\/script")
    style = (assets / "app.css").read_text().replace("</style", "<\\/style")
    data = base64.b64encode(scene.data).decode("ascii")
    page = (
        '<!doctype html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{html.escape(run.resolve().name)} · panogs viewer</title>\n<style>{style}</style>\n</head>\n"
        '<body class="pgs-standalone">\n<main id="viewer"></main>\n'
        f'<script id="panogs-scene" type="application/octet-stream">{data}</script>\n'
        f"<script>{script}</script>\n</body>\n</html>\n"
    )
    size = len(page.encode())
    if size > max_bytes:
        raise InputError(
            f"{out}: the offline file would be {size:,} bytes, over the limit of {max_bytes:,} "
            f"({scene.count:,} primitives); lower --max-primitives (now {max_primitives:,}) or raise --max-bytes"
        )
    Path(out).write_text(page)
    return {"count": scene.count, "total": scene.total, "bytes": size}


def describe(stats: dict[str, int], out: str | Path) -> str:
    """One line for the terminal."""
    kept = f"{stats['count']:,} primitives" + (
        f" (decimated from {stats['total']:,})" if stats["total"] > stats["count"] else ""
    )
    return f"wrote {out}: {kept}, {stats['bytes'] / 1e6:.1f} MB; open it in any browser, offline"
