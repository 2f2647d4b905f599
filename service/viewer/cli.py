"""``panogs view`` and ``panogs export-html``; added to the ``panogs`` CLI with the service commands."""

from __future__ import annotations

import argparse
import sys
import webbrowser
from pathlib import Path
from typing import Any

from service.viewer.export_html import DEFAULT_MAX_BYTES, DEFAULT_MAX_PRIMITIVES


def add_viewer_commands(subparsers: Any) -> None:
    """Add ``view`` and ``export-html`` to an argparse subparsers object."""
    p = subparsers.add_parser("view", help="open a finished run folder in the 3D viewer (served on 127.0.0.1)")
    p.add_argument("run", help="the --out folder of a run")
    p.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (0: any free port)")
    p.add_argument("--open", action="store_true", help="open the viewer in the default browser")
    p.add_argument("--model-path", help="text encoder weights for free-text queries (class names need none)")
    p.set_defaults(func=cmd_view)

    p = subparsers.add_parser("export-html", help="write a finished run as one self-contained offline HTML file")
    p.add_argument("run", help="the --out folder of a run")
    p.add_argument("out", help="the .html file to write")
    p.add_argument("--max-primitives", type=int, default=DEFAULT_MAX_PRIMITIVES, help="decimate above this")
    p.add_argument("--max-bytes", type=int, default=DEFAULT_MAX_BYTES, help="refuse a larger file")
    p.set_defaults(func=cmd_export_html)


def cmd_view(args: argparse.Namespace) -> int:
    """Serve the viewer until Ctrl-C and print its URL."""
    from service.encoder import EncoderProcess
    from service.viewer.local import RunViewer, serve

    encoder = EncoderProcess(args.model_path)
    run = RunViewer(Path(args.run), encoder)

    def ready(url: str) -> None:
        sys.stdout.write(f"panogs view: {run.scene.count:,} primitives of {args.run} at {url}  (Ctrl-C stops)\n")
        sys.stdout.flush()
        if args.open:
            webbrowser.open(url)

    try:
        serve(run, args.port, ready)
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        sys.stderr.write(f"panogs view: cannot listen on 127.0.0.1:{args.port} ({exc.strerror}); try --port 0\n")
        return 2
    finally:
        encoder.close()
    return 0


def cmd_export_html(args: argparse.Namespace) -> int:
    """Write the offline file."""
    from service.viewer.export_html import describe, export_html

    stats = export_html(args.run, args.out, max_primitives=args.max_primitives, max_bytes=args.max_bytes)
    sys.stdout.write(describe(stats, args.out) + "\n")
    return 0
