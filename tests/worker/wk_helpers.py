"""Helpers of the worker tests: read and change a job row directly."""

from __future__ import annotations

import uuid
from typing import Any

from service.db.models import Job
from service.db.session import get_session_factory, session_scope
from service.settings import Settings


def read_job(settings: Settings, job_id: uuid.UUID) -> Job:
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        _ = job.artifacts  # load before the session closes
        return job


def update_job(settings: Settings, job_id: uuid.UUID, **values: Any) -> None:
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        for k, v in values.items():
            setattr(job, k, v)
        session.commit()
