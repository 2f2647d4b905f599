"""What a run hands back: :class:`PipelineResult`, where its Gaussian fit stands, and the callbacks' types.

Shared by the untiled run (:mod:`panogs_core.pipeline.run`), the report writer (:mod:`panogs_core.pipeline.report`)
and the tiled run (:mod:`panogs_core.tiling.runner`).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from panogs_core.pipeline.profiling import StageStats


class FitState(enum.StrEnum):
    """Where a run's Gaussian fit stands: report.json's ``appearance.state``, and a job's ``fit_state`` in the
    service (one enum for both: docs/gaussians.md, "Results before the fit"). A member is its string."""

    RUNNING = "running"  # the results are written; the fit goes on and gaussians.ply is the initialisation
    SUCCEEDED = "succeeded"  # gaussians.ply is the fitted scene
    SKIPPED = "skipped"  # no fit was made (appearance.enabled false, no colour frame); gaussians.ply is final
    FAILED = "failed"  # the fit raised; the results stand, gaussians.ply is the initialisation
    CANCELED = "canceled"  # the run was stopped during the fit; the results stand, a re-run resumes the fit

    @property
    def scene_ready(self) -> bool:
        """True when gaussians.ply is final and renders may be made from it."""
        return self in (FitState.SUCCEEDED, FitState.SKIPPED)


# The members under the names the pipeline's modules use.
FIT_RUNNING = FitState.RUNNING
FIT_SUCCEEDED = FitState.SUCCEEDED
FIT_SKIPPED = FitState.SKIPPED
FIT_FAILED = FitState.FAILED
FIT_CANCELED = FitState.CANCELED
FIT_STATES = tuple(FitState)

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
    results_s: float = 0.0  # wall time to the results (their files written, before the fit); 0 until then

    @property
    def fit_state(self) -> str:
        """Where the Gaussian fit stands, one of ``FIT_STATES``."""
        return str(self.appearance.get("state", FIT_RUNNING))


# ``on_results(result)``: called once a run's results are written, before the fit; may raise ``Cancelled``.
ResultsFn = Callable[[PipelineResult], None]
