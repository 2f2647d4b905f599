"""How ``panogs run`` shows progress: bars on a terminal, one line per stage with its time anywhere else (a CI log,
``make demo > log``), nothing with ``--quiet``."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest

from panogs_core.cli.display import StageLines, stage_reporter
from panogs_core.pipeline.run import STAGES

REPO = Path(__file__).resolve().parents[2]


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class TerminalStream(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_one_line_per_stage_with_its_time() -> None:
    stream, clock = io.StringIO(), FakeClock()
    lines = StageLines(stream, clock)
    for stage, seconds in (("primitives", 1.3), ("fusion", 12.0)):
        for done in range(101):  # a stage reports many steps; none of them may print
            lines(stage, done, 100)
            clock.now += seconds / 101
    lines.close()
    lines.close()  # closing twice writes nothing more
    assert stream.getvalue().splitlines() == [f"{'primitives':>16}: 1.3 s", f"{'fusion':>16}: 12.0 s"]
    assert "\r" not in stream.getvalue()


def test_reporter_follows_the_stream() -> None:
    assert isinstance(stage_reporter(False, io.StringIO()), StageLines)
    assert not isinstance(stage_reporter(False, TerminalStream()), StageLines)
    quiet = io.StringIO()
    reporter = stage_reporter(True, quiet)
    reporter("primitives", 0, 1)
    reporter.close()
    assert quiet.getvalue() == ""


@pytest.mark.slow
def test_run_into_a_log_prints_a_line_per_stage(tmp_path: Path, synth_tiny: Path) -> None:
    """The real command with stderr to a pipe, as in ``make demo > log``."""
    scene = synth_tiny  # the session's ``panogs synth --preset tiny``, only read
    short = ["--set", "language_field.epochs=1", "--set", "language_field.min_steps=1"]  # the log is the point
    short += ["--set", "appearance.iterations=2"]
    run = [sys.executable, "-m", "panogs_core.cli", "run", str(scene), "--out", str(tmp_path / "run"), *short]
    # Bytes, not text: text mode would turn the carriage returns of a redrawn bar into newlines.
    done = subprocess.run(run, cwd=REPO, capture_output=True, timeout=600)
    stderr = done.stderr.decode()
    assert done.returncode == 0, stderr[-3000:]
    assert "\r" not in stderr, "a progress bar redrew itself into the log"
    lines = [line.split(":")[0].strip() for line in stderr.splitlines() if line.endswith(" s")]
    assert lines == [stage for stage in STAGES if stage in lines]
    assert {"validate", "primitives", "clustering", "labeling", "export"} <= set(lines)
    assert len(lines) == len(set(lines)), "each stage once"
