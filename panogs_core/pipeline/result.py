"""What a run hands back: :class:`PipelineResult`, where its Gaussian fit stands, and the callbacks' types.

Shared by the untiled run (:mod:`panogs_core.pipeline.run`), the report writer (:mod:`panogs_core.pipeline.report`)
and the tiled run (:mod:`panogs_core.tiling.runner`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from panogs_core.pipeline.profiling import StageStats

# report.json's ``appearance.state``: where the Gaussian fit stands (docs/gaussians.md, "Results before the fit").
FIT_RUNNING = "running"  # the results are written; the fit goes on and gaussians.ply is the initialisation
FIT_SUCCEEDED = "succeeded"  # gaussians.ply is the fitted scene
FIT_SKIPPED = "skipped"  # no fit was made (appearance.enabled false, no colour frame); gaussians.ply is final
FIT_FAILED = "failed"  # the fit raised; the results stand, gaussians.ply is the initialisation
FIT_CANCELED = "canceled"  # the run was stopped during the fit; the results stand, a re-run resumes the fit
FIT_STATES = (FIT_RUNNING, FIT_SUCCEEDED, FIT_SKIPPED, FIT_FAILED, FIT_CANCELED)

# ``on_progress(stage, done, total)`` of a run; may raise ``Cancelled`` to stop it.
StageProgressFn = Callable[[str, int, int], None]


@dataclass
class PipelineResult:
    """What a run produced. Files are in ``out_dir``; arrays are the in-memory copies."""

    out_dir: Path
    scene_name: str
    num_primitives: int
    instances: list[dict[str, Any]]
    timings: list[StageStats]
    metrics: dict[str, Any] | None = None
    files: dict[str, Path] = field(default_factory=dict)
    unseen: dict[str, int] = field(default_factory=dict)  # primitives no key frame saw, and how each was labelled
    appearance: dict[str, Any] = field(default_factory=dict)  # the Gaussian scene's fit: state, PSNR before/after
    total_s: float = 0.0  # wall time of the run so far

    @property
    def fit_state(self) -> str:
        """Where the Gaussian fit stands, one of ``FIT_STATES``."""
        return str(self.appearance.get("state", FIT_RUNNING))


# ``on_results(result)``: called once a run's results are written, before the fit; may raise ``Cancelled``.
ResultsFn = Callable[[PipelineResult], None]
