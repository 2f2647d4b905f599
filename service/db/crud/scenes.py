"""Scene queries outside a tenant's scope (the worker's)."""

from __future__ import annotations

import uuid

from sqlalchemy.orm import Session

from service.db.models import Scene


def get_scene(session: Session, scene_id: uuid.UUID) -> Scene | None:
    """A scene by id (worker side; no tenant scope)."""
    return session.get(Scene, scene_id)
