"""Making a scene from a complete upload: validate with the core validator, keep it only if it is valid.

``panogs_core.io.bundle.reader.open_bundle`` extracts the archive safely (paths that leave the root, links, archive
bombs) and checks every rule of docs/scene_format.md, reporting every problem at once, within the limits of the
settings (JSON depth, size and integers; pixels per image: each image's header is read before it is decoded; a
CPU budget per bundle). It runs in a child process, a few at a time (``service.bundle_check``). A refused bundle
leaves nothing behind: the extraction folder, the archive and the upload are deleted. Problems name files
relative to the bundle, never where the service stores it; one that passes a limit is followed by a line naming
the limit's setting.
"""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from sqlalchemy.orm import Session

from panogs_core.errors import BundleError
from service.bundle_check import BundleOpener, OpenedBundle, OpenRequest
from service.db import crud
from service.db.models import Scene, Upload, UploadState
from service.errors import Conflict, InvalidBundle
from service.settings import Settings
from service.storage import Storage, dir_size
from service.storage.extraction import Extraction
from service.stored_text import printable_text
from service.uploads import discard_upload

if TYPE_CHECKING:
    from panogs_core.io.bundle import BundleLimits

# The words each limit's problem line uses (panogs_core.bounded_json, panogs_core.io.bundle.reader), and its setting.
LIMIT_SETTINGS = {
    "JSON depth limit": "PANOGS_MAX_JSON_DEPTH",
    "JSON size limit": "PANOGS_BUNDLE_MAX_JSON_BYTES",
    "JSON integer limit": "PANOGS_MAX_JSON_INT_DIGITS",
    "pixel limit": "PANOGS_MAX_IMAGE_PIXELS",
    "CPU budget": "PANOGS_VALIDATION_CPU_S (per GiB of archive)",
}


def bundle_limits(settings: Settings) -> BundleLimits:
    """What a bundle's files may declare, from the settings."""
    from panogs_core.bounded_json import JsonLimits
    from panogs_core.io.bundle import BundleLimits

    json_limits = JsonLimits(
        max_depth=settings.max_json_depth,
        max_bytes=settings.bundle_max_json_bytes,
        max_int_digits=settings.max_json_int_digits,
    )
    return BundleLimits(json=json_limits, max_image_pixels=settings.max_image_pixels)


def limit_hints(problems: list[str]) -> list[str]:
    """One line per limit that ``problems`` pass, naming its setting."""
    return [
        f"the {words} is set by {setting}"
        for words, setting in LIMIT_SETTINGS.items()
        if any(words in problem for problem in problems)
    ]


def create_scene(
    session: Session,
    storage: Storage,
    upload: Upload,
    name: str | None,
    opener: BundleOpener,
    *,
    max_bytes: int | None = None,
    max_files: int | None = None,
    settings: Settings | None = None,
) -> Scene:
    """Validate and extract ``upload`` into a new scene of the upload's tenant, in one of ``opener``'s children.

    ``settings`` gives the limits of the bundle's JSON files and images (default: the core's).

    Raises:
        Conflict: the upload is not complete, or was already made into a scene.
        InvalidBundle: the bundle breaks the format; ``problems`` lists every problem. Nothing is kept.
        ServiceUnavailable: every validation slot is taken, or the host too busy to finish it; the upload is kept.
    """
    if name is not None:
        printable_text(name, "name")
    with opener.slot():
        return _create(session, storage, upload, name, opener, _limits(max_bytes, max_files), settings)


def _create(
    session: Session,
    storage: Storage,
    upload: Upload,
    name: str | None,
    opener: BundleOpener,
    limits: dict[str, int],
    settings: Settings | None,
) -> Scene:
    if upload.state != UploadState.COMPLETE or not crud.set_upload_state(
        session, upload.id, UploadState.COMPLETE, UploadState.CONSUMED
    ):
        raise Conflict(
            f"upload {upload.id} is {upload.state.value} ({upload.offset} of {upload.length} bytes); "
            "a scene needs a complete upload that no scene was made from"
        )
    scene_id = uuid.uuid4()
    with storage.extraction(upload.path, scene_id) as extraction:
        if extraction is None:
            _refuse_not_an_archive(session, storage, upload)
        try:
            scene = _validated(upload, name, extraction, scene_id, opener, settings, limits)
            extraction.keep()
            session.add(scene)
            session.commit()
        except BundleError as exc:
            session.rollback()
            extraction.refuse()
            discard_upload(session, storage, upload)
            raise _invalid(exc) from exc
        except BaseException:
            # Not the bundle's fault (disk, database): undo, so that the same upload can be tried again.
            session.rollback()
            extraction.undo()
            crud.set_upload_state(session, upload.id, UploadState.CONSUMED, UploadState.COMPLETE)
            raise
        extraction.done()  # extracted and stored: the archive's bytes are done with
    return scene


def _limits(max_bytes: int | None, max_files: int | None) -> dict[str, int]:
    return {k: v for k, v in (("max_bytes", max_bytes), ("max_files", max_files)) if v is not None}


def _refuse_not_an_archive(session: Session, storage: Storage, upload: Upload) -> NoReturn:
    discard_upload(session, storage, upload)
    raise InvalidBundle(
        "the upload is not a bundle archive; nothing was kept",
        problems=[f"{upload.filename or 'upload'}: not a .zip, .tar or .tar.gz archive (by its first bytes)"],
    )


def _invalid(exc: BundleError) -> InvalidBundle:
    problems = list(exc.problems)
    return InvalidBundle(
        f"the bundle has {len(problems)} problem(s); nothing was kept", problems=problems + limit_hints(problems)
    )


def _validated(
    upload: Upload,
    name: str | None,
    extraction: Extraction,
    scene_id: uuid.UUID,
    opener: BundleOpener,
    settings: Settings | None,
    limits: dict[str, int],
) -> Scene:
    """Extract and check the archive into the extraction's folder; the scene's row (``bundle_path``: the bundle's
    folder, as stored)."""
    from panogs_core.io.bundle import BundleLimits

    request = OpenRequest(
        archive=str(extraction.archive),
        workdir=str(extraction.workdir),
        limits=bundle_limits(settings) if settings is not None else BundleLimits(),
        max_bytes=limits.get("max_bytes"),
        max_files=limits.get("max_files"),
    )
    bundle: OpenedBundle = opener.open(request, upload.filename or "upload")
    if name is None:  # the bundle's own name; a refusal keeps the upload, to retry with a "name"
        printable_text(bundle.name, 'scene.json: name (give a printable "name" in the request instead)')
    return Scene(
        id=scene_id,
        api_key_id=upload.api_key_id,
        name=(name or bundle.name)[:255],
        feature_dim=bundle.feature_dim,
        feature_space=bundle.feature_space,
        num_frames=bundle.num_frames,
        has_vocabulary=bundle.has_vocabulary,
        has_ground_truth=bundle.has_ground_truth,
        has_feature_maps=bundle.has_feature_maps,
        has_mask_maps=bundle.has_mask_maps,
        bundle_path=extraction.bundle_key(Path(bundle.root)),
        bundle_sha256=upload.sha256,
        size_bytes=dir_size(extraction.workdir),
    )
