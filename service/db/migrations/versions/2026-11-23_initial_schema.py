"""Initial schema: api_key, upload, scene, job, artifact.

Revision ID: 0001_initial
Revises:
Created: 2026-11-23

Reviewed: tables match service/db/models.py column for column (alembic check finds no drift); enums are
VARCHAR(16) without CHECK constraints (a new state needs no migration); downgrade() drops the five tables in
reverse dependency order, which also drops their indexes.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001_initial"
down_revision: str | Sequence[str] | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _id() -> sa.Column:
    return sa.Column("id", sa.Uuid(), nullable=False)


def _tenant() -> sa.Column:
    return sa.Column("api_key_id", sa.Uuid(), nullable=False)


def _time(name: str, *, nullable: bool = True) -> sa.Column:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def _stamps() -> list[sa.Column]:
    return [_time("created_at", nullable=False), _time("updated_at", nullable=False)]


def _tenant_fk(table: str) -> sa.ForeignKeyConstraint:
    return sa.ForeignKeyConstraint(
        ["api_key_id"], ["api_key.id"], name=op.f(f"fk_{table}_api_key_id_api_key"), ondelete="CASCADE"
    )


def upgrade() -> None:
    op.create_table(
        "api_key",
        _id(),
        sa.Column("name", sa.String(100), nullable=False),
        sa.Column("prefix", sa.String(16), nullable=False),
        sa.Column("key_hash", sa.String(64), nullable=False),
        _time("revoked_at"),
        *_stamps(),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_api_key")),
        sa.UniqueConstraint("prefix", name=op.f("uq_api_key_prefix")),
    )
    op.create_table(
        "upload",
        _id(),
        _tenant(),
        sa.Column("filename", sa.String(255), nullable=True),
        sa.Column("length", sa.BigInteger(), nullable=False),
        sa.Column("offset", sa.BigInteger(), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("expected_sha256", sa.String(64), nullable=True),
        sa.Column("sha256", sa.String(64), nullable=True),
        sa.Column("path", sa.String(512), nullable=False),
        _time("completed_at"),
        *_stamps(),
        _tenant_fk("upload"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_upload")),
    )
    op.create_index(op.f("ix_upload_api_key_id"), "upload", ["api_key_id"])
    op.create_table(
        "scene",
        _id(),
        _tenant(),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("feature_dim", sa.Integer(), nullable=False),
        sa.Column("feature_space", sa.String(64), nullable=False),
        sa.Column("num_frames", sa.Integer(), nullable=False),
        sa.Column("has_vocabulary", sa.Boolean(), nullable=False),
        sa.Column("has_ground_truth", sa.Boolean(), nullable=False),
        sa.Column("bundle_path", sa.String(512), nullable=False),
        sa.Column("bundle_sha256", sa.String(64), nullable=True),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        *_stamps(),
        _tenant_fk("scene"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_scene")),
    )
    op.create_index(op.f("ix_scene_api_key_id"), "scene", ["api_key_id"])
    op.create_table(
        "job",
        _id(),
        _tenant(),
        sa.Column("scene_id", sa.Uuid(), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("stage", sa.String(64), nullable=True),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("stage_timings", sa.JSON(), nullable=False),
        sa.Column("config", sa.JSON(), nullable=False),
        sa.Column("vocabulary", sa.Text(), nullable=True),
        sa.Column("queue", sa.String(64), nullable=False),
        sa.Column("idempotency_key", sa.String(255), nullable=True),
        sa.Column("request_hash", sa.String(64), nullable=False),
        sa.Column("error_type", sa.String(100), nullable=True),
        sa.Column("error_message", sa.Text(), nullable=True),
        sa.Column("cancel_requested", sa.Boolean(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("lease", sa.String(64), nullable=True),
        sa.Column("worker", sa.String(255), nullable=True),
        _time("enqueued_at"),
        _time("heartbeat_at"),
        _time("started_at"),
        _time("finished_at"),
        *_stamps(),
        _tenant_fk("job"),
        sa.ForeignKeyConstraint(["scene_id"], ["scene.id"], name=op.f("fk_job_scene_id_scene"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_job")),
        sa.UniqueConstraint("api_key_id", "idempotency_key", name=op.f("uq_job_api_key_id_idempotency_key")),
    )
    op.create_index(op.f("ix_job_api_key_id"), "job", ["api_key_id"])
    op.create_index(op.f("ix_job_scene_id"), "job", ["scene_id"])
    op.create_index("ix_job_state_heartbeat_at", "job", ["state", "heartbeat_at"])
    op.create_table(
        "artifact",
        _id(),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("path", sa.String(512), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("media_type", sa.String(100), nullable=False),
        *_stamps(),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], name=op.f("fk_artifact_job_id_job"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_artifact")),
        sa.UniqueConstraint("job_id", "name", name=op.f("uq_artifact_job_id_name")),
    )
    op.create_index(op.f("ix_artifact_job_id"), "artifact", ["job_id"])


def downgrade() -> None:
    # Dependants first; dropping a table drops its indexes and constraints with it.
    for table in ("artifact", "job", "scene", "upload", "api_key"):
        op.drop_table(table)
