"""The 2D models a job names, and whether a scene's bundle brings its own maps.

Revision ID: 0008_map_models
Revises: 0007_job_tiles
Created: 2026-12-05

Reviewed: matches Job.maps, Scene.has_feature_maps and Scene.has_mask_maps in service/db/models.py (alembic check
finds no drift). ``job.maps`` is a nullable JSON object of entry names (never paths); existing jobs keep NULL: they
ran on the bundle's maps. The scene columns are NOT NULL with a server default of true: every scene made before
this revision came from a bundle that had to carry both kinds of map. Downgrade drops the three columns; a scene
without maps then reads as one with them, so its next job fails in the worker instead of being refused by the API
(delete such scenes before downgrading).
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008_map_models"
down_revision: str | Sequence[str] | None = "0007_job_tiles"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("maps", sa.JSON(none_as_null=True), nullable=True))
    with op.batch_alter_table("scene") as batch:
        batch.add_column(sa.Column("has_feature_maps", sa.Boolean(), server_default=sa.true(), nullable=False))
        batch.add_column(sa.Column("has_mask_maps", sa.Boolean(), server_default=sa.true(), nullable=False))


def downgrade() -> None:
    with op.batch_alter_table("scene") as batch:
        batch.drop_column("has_mask_maps")
        batch.drop_column("has_feature_maps")
    with op.batch_alter_table("job") as batch:
        batch.drop_column("maps")
