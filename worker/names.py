"""Task names and queues: the API enqueues by name, so it never imports task code."""

from __future__ import annotations

from enum import StrEnum


class TaskName(StrEnum):
    """Registered task names."""

    RUN_JOB = "panogs.run_job"


class QueueName(StrEnum):
    """The queues workers consume; jobs go to ``Settings.job_queue``."""

    CPU = "cpu"
    GPU = "gpu"
