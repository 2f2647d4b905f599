"""What ``panogs`` shows on the terminal: a run's progress (bars, one line per stage, or nothing) and the tables of
its instances, metrics and appearance fit. Plain text from plain dicts: nothing here imports numpy or torch."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol, TextIO

FITTING_LINE = "the results are written; fitting the Gaussian scene (gaussians.ply) ..."


class StageReporter(Protocol):
    """Shows a run's progress: called as ``on_progress(stage, done, total)``, closed when the run ends."""

    def __call__(self, stage: str, done: int, total: int) -> None: ...

    def close(self) -> None: ...


class _Silent:
    """``--quiet``: shows nothing."""

    def __call__(self, stage: str, done: int, total: int) -> None:
        return None

    def close(self) -> None:
        return None


class StageLines:
    """One line per finished stage with its wall time, for a stream that is not a terminal.

    A log (CI, ``make demo > log``) keeps every frame of a progress bar, hundreds per stage; this writes each
    stage once, when the next one starts or the run ends.
    """

    def __init__(self, stream: TextIO, clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream
        self.clock = clock
        self.stage: str | None = None
        self.started = 0.0

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage != self.stage:
            self.close()
            self.stage, self.started = stage, self.clock()

    def close(self) -> None:
        """Write the line of the stage in progress, if any."""
        if self.stage is None:
            return
        self.stream.write(f"{self.stage:>16}: {self.clock() - self.started:.1f} s\n")
        self.stream.flush()
        self.stage = None


def stage_reporter(quiet: bool, stream: TextIO) -> StageReporter:
    """Nothing with ``--quiet``; progress bars on a terminal; one line per stage anywhere else."""
    if quiet:
        return _Silent()
    if stream.isatty():
        return _StageBars(stream)
    return StageLines(stream)


class _StageBars:
    """One tqdm bar per stage, redrawn in place (for a terminal)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.stage: str | None = None
        self.bar: Any = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = tqdm(
                total=max(total, 1), desc=f"{stage:>16}", unit="step", leave=True, file=self.stream, dynamic_ncols=True
            )
        if self.bar is not None:
            if total != self.bar.total:
                self.bar.total = max(total, 1)
            self.bar.n = min(done, self.bar.total)
            self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def format_instances(instances: list[dict[str, Any]], limit: int = 40) -> str:
    """A fixed-width table of instances (things first, by class then size)."""
    rows = sorted(instances, key=lambda i: (i["kind"] != "thing", i["class_name"], -i["num_points"]))
    lines = [f"{'id':>4}  {'class':<16} {'kind':<5} {'score':>5} {'points':>7}  centroid (m)"]
    for inst in rows[:limit]:
        c = inst["centroid"]
        lines.append(
            f"{inst['id']:>4}  {inst['class_name'][:16]:<16} {inst['kind']:<5} {inst['score']:>5.2f} "
            f"{inst['num_points']:>7}  ({c[0]:6.2f}, {c[1]:6.2f}, {c[2]:6.2f})"
        )
    if len(rows) > limit:
        lines.append(f"... {len(rows) - limit} more in instances.json")
    return "\n".join(lines)


def format_appearance(summary: dict[str, Any]) -> str:
    """One line on the Gaussian scene's fit: PSNR before and after, why it did not run, or how it failed ("" without
    a fit)."""
    if summary.get("state") in ("failed", "canceled"):
        return (
            f"gaussians: the fit {summary['state']} ({summary.get('error', '')}); the results stand, gaussians.ply "
            "holds the initialisation"
        )
    if summary.get("psnr_after") is not None:
        return (
            f"gaussians: PSNR {summary['psnr_before']:.2f} -> {summary['psnr_after']:.2f} dB on "
            f"{summary['evaluated_on']} frames ({summary['iterations']} iterations)"
        )
    return f"gaussians: {summary['note']}" if summary.get("note") else ""


def format_metrics(metrics: dict[str, Any]) -> str:
    """One line per evaluation mode."""

    def num(value: Any) -> str:
        return "  n/a" if value is None else f"{value:.3f}"

    lines = []
    for mode, m in metrics.items():
        lines.append(
            f"{mode:>8}: mIoU {num(m['miou'])}  mAcc {num(m['macc'])}  "
            f"PRQ(T) {num(m['prq_thing'])}  PRQ(S) {num(m['prq_stuff'])}"
        )
    return "\n".join(lines)
