"""Results before the fit: a job records its results, then follows its appearance fit.

Revision ID: 0004_job_results_before_fit
Revises: 0003_job_inline_vocabulary
Created: 2026-12-02

Reviewed: matches Job.results_at, Job.fit_state, Job.fit_progress and Job.fit_error in service/db/models.py (alembic
check finds no drift); all nullable, stored as plain strings and numbers like the job's state (no enum type, no
CHECK). A job that succeeded before this revision had its fit done before its results: it is given
``results_at = finished_at`` and ``fit_state = succeeded``, so its instances, queries, renders and gaussians.ply
answer as before; other rows keep NULL (no results recorded). Downgrade drops the four columns; a job that was in
its fit when downgraded still shows ``running`` and its results are refused until it succeeds, as before.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004_job_results_before_fit"
down_revision: str | Sequence[str] | None = "0003_job_inline_vocabulary"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("results_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("fit_state", sa.String(16), nullable=True))
        batch.add_column(sa.Column("fit_progress", sa.Float(), nullable=True))
        batch.add_column(sa.Column("fit_error", sa.Text(), nullable=True))
    job = sa.table(
        "job",
        sa.column("state", sa.String(16)),
        sa.column("finished_at", sa.DateTime(timezone=True)),
        sa.column("results_at", sa.DateTime(timezone=True)),
        sa.column("fit_state", sa.String(16)),
        sa.column("fit_progress", sa.Float()),
    )
    op.execute(
        job.update()
        .where(job.c.state == "succeeded")
        .values(results_at=job.c.finished_at, fit_state="succeeded", fit_progress=1.0)
    )


def downgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.drop_column("fit_error")
        batch.drop_column("fit_progress")
        batch.drop_column("fit_state")
        batch.drop_column("results_at")
