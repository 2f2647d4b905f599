"""An upload's multipart state (S3) in its row, moved with the offset, instead of an object per PATCH.

Revision ID: 0006_upload_multipart
Revises: 0005_job_cached_stages
Created: 2026-12-03

Reviewed: matches Upload.multipart in service/db/models.py (alembic check finds no drift): one nullable JSON
column. Existing rows keep NULL: local uploads never use it, and an S3 upload begun before this revision still
has its state in ``state-<offset>.json`` beside its parts, which the API reads for a row without one
(``service/storage/parts.py``); its next PATCH moves the state into the row. Downgrade drops the column: an S3
upload in progress then has no state the old code can read (its state objects are no longer written), so its
next PATCH is refused and the client starts the upload again; finished uploads lose nothing.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006_upload_multipart"
down_revision: str | Sequence[str] | None = "0005_job_cached_stages"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("upload") as batch:
        batch.add_column(sa.Column("multipart", sa.JSON(none_as_null=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("upload") as batch:
        batch.drop_column("multipart")
