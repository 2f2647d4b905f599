"""Inline vocabularies: a job's label set given in the request body instead of a name.

Revision ID: 0003_job_inline_vocabulary
Revises: 0002_app_session
Created: 2026-12-02

Reviewed: matches Job.vocabulary_classes and Job.vocabulary_embeddings in service/db/models.py (alembic check finds
no drift); both nullable, so existing rows keep their meaning (NULL: no inline vocabulary). A row whose
``vocabulary`` holds a path from before this revision is left as it is: the worker resolves built-in names only
and fails such a job with a message that does not repeat the path. Downgrade drops the two columns, and with them
any inline vocabulary: the jobs that had one would run with the bundle's label set if re-run.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003_job_inline_vocabulary"
down_revision: str | Sequence[str] | None = "0002_app_session"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("vocabulary_classes", sa.JSON(), nullable=True))
        batch.add_column(sa.Column("vocabulary_embeddings", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.drop_column("vocabulary_embeddings")
        batch.drop_column("vocabulary_classes")
