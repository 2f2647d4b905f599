"""The stages a job took from its scene's shared checkpoints instead of computing them.

Revision ID: 0005_job_cached_stages
Revises: 0004_job_results_before_fit
Created: 2026-12-03

Reviewed: matches Job.cached_stages in service/db/models.py (alembic check finds no drift): one nullable JSON
column, a list of stage names. Existing rows keep NULL, which the API shows as no stage cached (nothing was
recorded for them; their stages may have been reused, the row cannot tell). Downgrade drops the column; the jobs
lose which of their stages were reused, their timings and results stay.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005_job_cached_stages"
down_revision: str | Sequence[str] | None = "0004_job_results_before_fit"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("cached_stages", sa.JSON(none_as_null=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.drop_column("cached_stages")
