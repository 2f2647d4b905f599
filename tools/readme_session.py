"""Run the README's curl session ("For scripts, the same with curl") as written, and fail when any line fails.

The block is taken from README.md as it stands (the ```bash block after the line that starts with
``SESSION_INTRO``) and run by bash with ``set -euo pipefail`` in a fresh folder, so ``panogs-data`` (database,
broker, storage) and the key are new. Two things differ from a user's shell, each said here: the port is a free
one instead of 8000 (another server may hold it), and ``.venv/bin/panogs`` is a link to the ``panogs`` of the
Python that runs this script. Every curl of the block carries ``--fail-with-body``, so an error answer fails its
line. A background server left by a failing line is stopped on exit. At the end the files the session wrote must
be what they say: ``panoptic.ply`` a PLY, ``view.png`` a PNG.

    .venv/bin/python tools/readme_session.py            # prints the session's output; exit 1 on a failure
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
SESSION_INTRO = "For scripts, the same with curl"
README_PORT = "8000"
TIMEOUT_S = 900  # the block polls the job for at most 10 minutes, plus synth, start and downloads
PROLOGUE = """set -euo pipefail
trap 'for p in $(jobs -p); do kill "$p" 2>/dev/null || true; done; wait || true' EXIT
"""
EXPECTED_FILES = {"panoptic.ply": b"ply\n", "view.png": b"\x89PNG\r\n\x1a\n"}  # name: first bytes


def session_block(readme: Path = README) -> str:
    """The bash block of the curl session, as written in the README."""
    text = readme.read_text()
    start = text.find(SESSION_INTRO)
    if start < 0:
        raise SystemExit(f"{readme}: no line starting with {SESSION_INTRO!r}")
    found = re.search(r"```bash\n(.*?)```", text[start:], re.DOTALL)
    if found is None:
        raise SystemExit(f"{readme}: no ```bash block after {SESSION_INTRO!r}")
    return found.group(1)


def on_port(block: str, port: int) -> str:
    """The block with the README's port replaced by ``port`` (in ``--port 8000`` and ``:8000``)."""
    replaced = re.sub(rf"(--port |:){README_PORT}\b", rf"\g<1>{port}", block)
    if replaced == block:
        raise SystemExit(f"the README's session names no port {README_PORT}; update {Path(__file__).name}")
    return replaced


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def check_outputs(workdir: Path) -> list[str]:
    """What is wrong with the files the session wrote (empty when nothing)."""
    problems = []
    for name, magic in EXPECTED_FILES.items():
        path = workdir / name
        if not path.is_file():
            problems.append(f"{name}: not written")
        elif not path.read_bytes().startswith(magic):
            problems.append(f"{name}: not a {name.rsplit('.', 1)[1].upper()} file: {path.read_bytes()[:200]!r}")
    return problems


def run_session(workdir: Path, timeout_s: float = TIMEOUT_S) -> tuple[int, str]:
    """Run the session in ``workdir`` (made empty by the caller); (exit status, output)."""
    venv_bin = workdir / ".venv" / "bin"
    venv_bin.mkdir(parents=True)
    (venv_bin / "panogs").symlink_to(Path(sys.executable).with_name("panogs"))
    script = PROLOGUE + on_port(session_block(), free_port())
    env = {k: v for k, v in os.environ.items() if not k.startswith("PANOGS_")}  # embedded defaults, as a new user
    env.update({"HF_HUB_OFFLINE": "1", "TOKENIZERS_PARALLELISM": "false"})
    # Its own process group: on a timeout the block's server and worker are stopped with it.
    proc = subprocess.Popen(["bash", "-c", script], cwd=workdir, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    try:
        output, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGTERM)
        output, _ = proc.communicate()
        return 124, output + f"\nthe README session ran past {timeout_s:.0f} s"
    if proc.returncode == 0:
        problems = check_outputs(workdir)
        if problems:
            return 1, output + "\n" + "\n".join(problems)
    return proc.returncode, output


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", action="store_true", help="keep the session's folder and print its path")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="panogs-readme-session-"))
    status, output = run_session(workdir)
    sys.stdout.write(output)
    if args.keep:
        sys.stdout.write(f"\nthe session's folder: {workdir}\n")
    else:
        shutil.rmtree(workdir, ignore_errors=True)
    sys.stdout.write(f"\nREADME session: {'ok' if status == 0 else f'FAILED (exit {status})'}\n")
    return 0 if status == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
