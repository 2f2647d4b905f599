"""The README's demo output is a log of ``make demo`` as tools/readme_demo.py writes it (``make readme``): the four
commands, a line per stage, the summary, the Gaussian scene's PSNR line, the instance table, the metrics, the
query's answer and the render, each line in the form the CLI prints. The patterns are checked against the CLI's
own formatting, so a change of the CLI's output fails here until the README is regenerated. (The numbers
themselves: ``make readme-check``.)"""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest
from tool_modules import load_tool

from panogs_core.cli.display import FITTING_LINE, StageLines, format_instances, format_metrics
from panogs_core.pipeline.run import STAGES

REPO = Path(__file__).resolve().parents[2]


tool = load_tool("readme_demo")

NUM = r"[ \d.-]"
# One pattern per kind of line, named by a token; the block must spell a sentence of tokens (SHAPE).
PATTERNS = {
    "stage": r" *\w+: \d+\.\d s",
    "synth": r"wrote synthetic scene \(small, default, seed 0\) to demo/scene",
    "summary": r"\S+: \d+ primitives, \d+ instances, \d+\.\d s -> demo/run",
    "row": rf" *\d+  .{{16}} (thing|stuff) {NUM}{{5}} [ \d]{{7}}  \({NUM}{{6}}, {NUM}{{6}}, {NUM}{{6}}\)",
    "metric": r" *(standard|paper): mIoU (\d\.\d{3}|  n/a)  mAcc (\d\.\d{3}|  n/a)  "
    r"PRQ\(T\) (\d\.\d{3}|  n/a)  PRQ\(S\) (\d\.\d{3}|  n/a)",
    "query": r"query 'chair': \d+ instance\(s\)",
    "hit": r"  instance +\d+  .{16} score \d\.\d{3}  box \[\S+ \S+ \S+\] - \[\S+ \S+ \S+\]",
    "gaussians": r"gaussians: PSNR \d+\.\d\d -> \d+\.\d\d dB on (training|held-out) frames \(\d+ iterations\)",
    "fitting": re.escape(FITTING_LINE),
    "render": r"wrote (\w+\.png, )+\w+\.png to demo/render",
}
SHAPE = re.compile(
    # The results first (summary, instances, metrics), then the Gaussian fit's line: the fit runs after them.
    r"cmd_synth synth cmd_run (stage )+blank summary header (row )+(elided_row )?(row )?blank (metric ){2}"
    r"blank fitting gaussians "
    r"cmd_query query (hit )+(elided_hit )?cmd_render render "
)


def token(line: str) -> str:
    """The kind of a line of the block."""
    commands = {" ".join([tool.PANOGS_SHOWN, *c]): f"cmd_{c[0]}" for c in tool.DEMO_COMMANDS}
    fixed = {"": "blank", tool.ELIDED_ROW: "elided_row", tool.ELIDED_HIT: "elided_hit"}
    if line in commands:
        return commands[line]
    if line in fixed:
        return fixed[line]
    if line == format_instances([]).splitlines()[0]:
        return "header"
    for name, pattern in PATTERNS.items():
        if re.fullmatch(pattern, line):
            return name
    return f"<unknown: {line!r}>"


def readme_lines() -> list[str]:
    text = (REPO / "README.md").read_text()
    assert text.count(tool.BEGIN) == 1, "one begin marker"
    assert text.count(tool.END) == 1, "one end marker"
    inner = tool.readme_block(text).splitlines()[1:-1]
    assert inner[0] == "```"
    assert inner[-1] == "```"
    return inner[1:-1]


def test_patterns_match_what_the_cli_prints() -> None:
    instances = [
        {"id": 7, "class_name": "other furniture", "kind": "thing", "score": 0.875, "num_points": 1882,
         "centroid": [0.24, -2.74, 10.85]},
        {"id": 12, "class_name": "wall", "kind": "stuff", "score": 1.0, "num_points": 13631,
         "centroid": [2.9, 1.8, 1.4]},
    ]  # fmt: skip
    for row in format_instances(instances).splitlines()[1:]:
        assert re.fullmatch(PATTERNS["row"], row), row
    metrics = {"standard": {"miou": 0.95, "macc": 0.9, "prq_thing": None, "prq_stuff": 0.5}}
    metrics["paper"] = metrics["standard"]
    for line in format_metrics(metrics).splitlines():
        assert re.fullmatch(PATTERNS["metric"], line), line
    stream, now = io.StringIO(), iter([0.0, 1.5, 1.5, 3.0])
    lines = StageLines(stream, clock=lambda: next(now))
    lines("superprimitives", 0, 1)
    lines("export", 0, 1)
    lines.close()
    for line in stream.getvalue().splitlines():
        assert re.fullmatch(PATTERNS["stage"], line), line


def test_readme_block_is_a_log_of_the_demo() -> None:
    lines = readme_lines()
    tokens = [token(line) for line in lines]
    unknown = [t for t in tokens if t.startswith("<unknown")]
    assert not unknown, f"lines the CLI does not print (run `make readme`): {unknown}"
    assert SHAPE.fullmatch("".join(f"{t} " for t in tokens)), f"out of order (run `make readme`): {tokens}"
    stages = [line.split(":")[0].strip() for line, t in zip(lines, tokens) if t == "stage"]
    assert stages == [s for s in STAGES if s in stages], "stages in pipeline order"


def test_elide_keeps_the_first_and_last_rows() -> None:
    header = format_instances([]).splitlines()[0]
    rows = [f"row {i}" for i in range(10)]
    hits = [f"  instance {i}" for i in range(5)]
    log = ["summary", header, *rows, "", "metrics", "query 'chair': 5 instance(s)", *hits]
    out = tool.elide(log)
    assert out == [
        "summary", header, "row 0", "row 1", "row 2", tool.ELIDED_ROW, "row 9", "", "metrics",
        "query 'chair': 5 instance(s)", "  instance 0", "  instance 1", tool.ELIDED_HIT,
    ]  # fmt: skip


@pytest.mark.parametrize("count", [1, 4])
def test_elide_leaves_short_tables_whole(count: int) -> None:
    header = format_instances([]).splitlines()[0]
    log = [header, *[f"row {i}" for i in range(count)], ""]
    assert tool.elide(log) == log


def test_write_then_check(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``make readme`` rewrites only the block; ``make readme-check`` passes on other times, fails on other
    results."""
    log = ["summary: 10 primitives, 2 instances, 3.1 s -> demo/run", "standard: mIoU 0.950"]
    monkeypatch.setattr(tool, "run_demo", lambda _workdir: list(log))
    readme = tmp_path / "README.md"
    readme.write_text(f"before\n{tool.BEGIN}\n```\nstale\n```\n{tool.END}\nafter\n")
    assert tool.main(["--readme", str(readme)]) == 0
    assert readme.read_text() == f"before\n{tool.block(log)}\nafter\n"
    log[0] = "summary: 10 primitives, 2 instances, 9.9 s -> demo/run"  # another run, another time
    assert tool.main(["--check", "--readme", str(readme)]) == 0
    log[1] = "standard: mIoU 0.788"  # other results
    assert tool.main(["--check", "--readme", str(readme)]) == 1


def _demo_log(miou: str, psnr: str, hits: list[str], rows: list[str], instances: int = 22) -> list[str]:
    header = format_instances([]).splitlines()[0]
    return [
        f"scene: 30347 primitives, {instances} instances, 29.7 s -> demo/run",
        f"gaussians: PSNR 12.64 -> {psnr} dB on training frames (118 iterations)",
        header, *rows, "",
        f"standard: mIoU {miou}  mAcc 0.972  PRQ(T) 0.921  PRQ(S) 0.973",
        f"query 'chair': {len(hits)} instance(s)", *hits,
    ]  # fmt: skip


def test_the_check_allows_the_noise_between_processors_and_nothing_more() -> None:
    """Another processor's BLAS moves the labels a little: other rows, hits and counts, metrics within 0.03."""
    rows = ["   5  bookshelf        thing  1.00    1397  (  5.31,   1.52,   0.93)"]
    hits = ["  instance    0  chair            score 0.996  box [0.73 3.42 0.00] - [1.27 3.85 0.92]"]
    readme = _demo_log("0.952", "23.81", hits * 2, rows)
    other_machine = _demo_log("0.955", "23.70", hits, rows * 3 + [tool.ELIDED_ROW], instances=21)
    assert tool.differences(readme, other_machine) == []
    assert tool.differences(readme, _demo_log("0.900", "23.81", hits, rows)), "mIoU 0.052 apart"
    assert tool.differences(readme, _demo_log("0.952", "22.81", hits, rows)), "PSNR 1 dB apart"
    renamed = [line.replace("standard:", "standard mode:") for line in readme]
    assert tool.differences(readme, renamed), "another line"
    assert tool.differences(readme, [*readme, "wrote color.png to demo/render"]), "a line more"
