"""What a job's tasks (its own, and a tiled job's merge) read and write of the job: the label set the pipeline
gets, and the artifact rows of the files it wrote."""

from __future__ import annotations

import uuid
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from panogs_core.io.run_folder import DOWNLOADABLE
from panogs_core.types import Vocabulary
from service.db.models import Artifact, Job
from service.storage import Storage, sha256_file

# The pipeline's outputs that become downloadable artifacts, with their media types (the run folder's declaration).
ARTIFACTS = {name: spec.media_type for name, spec in DOWNLOADABLE.items()}


def job_vocabulary(session: Session, job: Job) -> str | Vocabulary | None:
    """What the pipeline gets as the job's label set: a built-in name (the pipeline resolves names only), the
    job's inline classes and embeddings as a :class:`Vocabulary`, or None for the bundle's own; never a string that
    could name a file (docs/service.md "Which request fields reach the host").

    Raises:
        InputError: the stored value is not a built-in name (a row from before inline vocabularies that named a
            file: refused without repeating it), or the inline classes do not parse.
    """
    from panogs_core.language.label_sets import builtin_vocabulary, inline_vocabulary, is_builtin_name

    if job.vocabulary_classes is not None:
        embeddings = session.scalar(select(Job.vocabulary_embeddings).where(Job.id == job.id))
        return inline_vocabulary(job.vocabulary_classes, embeddings, source=f"job {job.id} vocabulary")
    if job.vocabulary is not None and not is_builtin_name(job.vocabulary):
        builtin_vocabulary(job.vocabulary)  # raises, with a message that names no path
    return job.vocabulary


def collect_artifacts(
    job_id: uuid.UUID, out_dir: Path, storage: Storage, *, exclude: frozenset[str] = frozenset()
) -> list[Artifact]:
    """Artifact rows for the pipeline outputs present in ``out_dir``, but those named in ``exclude``."""
    rows = []
    for name, media_type in ARTIFACTS.items():
        path = out_dir / name
        if path.is_file() and name not in exclude:
            rows.append(
                Artifact(
                    job_id=job_id,
                    name=name,
                    path=storage.job_prefix(job_id) + name,
                    size_bytes=path.stat().st_size,
                    sha256=sha256_file(path).hexdigest(),
                    media_type=media_type,
                )
            )
    return rows
