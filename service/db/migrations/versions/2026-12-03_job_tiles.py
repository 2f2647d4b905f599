"""Tiled jobs: the tiling a job asked for, and a row per tile (and one for the merge) with its own lease.

Revision ID: 0007_job_tiles
Revises: 0006_upload_multipart
Created: 2026-12-03

Reviewed: matches Job.tiling and JobTile in service/db/models.py (alembic check finds no drift). Existing jobs keep
a NULL ``tiling`` (not tiled) and have no tile rows, so they read as before. Downgrade drops the table and the
column: a tiled job that is still running loses its fan-in (its tiles' and merge's tasks find no row and stop),
so drain the queue first; finished tiled jobs keep their artifacts.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007_job_tiles"
down_revision: str | Sequence[str] | None = "0006_upload_multipart"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("tiling", sa.JSON(none_as_null=True), nullable=True))
    op.create_table(
        "job_tile",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("tile_index", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("name", sa.String(64), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("stage", sa.String(64), nullable=True),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("weight", sa.Float(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("lease", sa.String(64), nullable=True),
        sa.Column("worker", sa.String(255), nullable=True),
        sa.Column("enqueued_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("wall_s", sa.Float(), nullable=True),
        sa.Column("peak_rss_mb", sa.Float(), nullable=True),
        sa.Column("report", sa.JSON(none_as_null=True), nullable=True),
        sa.Column("error_type", sa.String(100), nullable=True),
        sa.Column("error_message", sa.Text(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], name=op.f("fk_job_tile_job_id_job"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_job_tile")),
        sa.UniqueConstraint("job_id", "tile_index", name=op.f("uq_job_tile_job_id_tile_index")),
    )
    op.create_index(op.f("ix_job_tile_job_id"), "job_tile", ["job_id"])
    op.create_index("ix_job_tile_state_heartbeat_at", "job_tile", ["state", "heartbeat_at"])


def downgrade() -> None:
    op.drop_table("job_tile")
    with op.batch_alter_table("job") as batch:
        batch.drop_column("tiling")
