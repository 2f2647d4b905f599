"""Making a scene from a complete upload: validate with the core validator, keep it only if it is valid.

``panogs_core.io.bundle.reader.open_bundle`` extracts the archive safely (paths that leave the root, links, archive
bombs) and checks every rule of docs/scene_format.md, reporting every problem at once, within the limits of the
settings (JSON depth, size and integers; pixels per image: each image's header is read before it is decoded). A
refused bundle leaves nothing behind: the extraction folder, the archive and the upload are deleted. Problems
name files relative to the bundle, never where the service stores it; one that passes a limit is followed by a
line naming the limit's setting.
"""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from sqlalchemy.orm import Session

from panogs_core.errors import BundleError
from service.db import crud
from service.db.models import Scene, Upload, UploadState
from service.errors import Conflict, InvalidBundle
from service.settings import Settings
from service.storage import Storage, archive_suffix, detect_archive, dir_size, upload_folder
from service.stored_text import printable_text
from service.uploads import discard_upload

if TYPE_CHECKING:
    from panogs_core.io.bundle import BundleLimits

# The words each limit's problem line uses (panogs_core.io.bounded_json, panogs_core.io.bundle.reader), and its setting.
LIMIT_SETTINGS = {
    "JSON depth limit": "PANOGS_MAX_JSON_DEPTH",
    "JSON size limit": "PANOGS_BUNDLE_MAX_JSON_BYTES",
    "JSON integer limit": "PANOGS_MAX_JSON_INT_DIGITS",
    "pixel limit": "PANOGS_MAX_IMAGE_PIXELS",
}


def bundle_limits(settings: Settings) -> BundleLimits:
    """What a bundle's files may declare, from the settings."""
    from panogs_core.io.bounded_json import JsonLimits
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
    *,
    max_bytes: int | None = None,
    max_files: int | None = None,
    settings: Settings | None = None,
) -> Scene:
    """Validate and extract ``upload`` into a new scene of the upload's tenant.

    ``settings`` gives the limits of the bundle's JSON files and images (default: the core's).

    Raises:
        Conflict: the upload is not complete, or was already made into a scene.
        InvalidBundle: the bundle breaks the format; ``problems`` lists every problem. Nothing is kept.
    """
    if name is not None:
        printable_text(name, "name")
    if upload.state != UploadState.COMPLETE or not crud.set_upload_state(
        session, upload.id, UploadState.COMPLETE, UploadState.CONSUMED
    ):
        raise Conflict(
            f"upload {upload.id} is {upload.state.value} ({upload.offset} of {upload.length} bytes); "
            "a scene needs a complete upload that no scene was made from"
        )
    if not storage.is_local:
        return _create_from_objects(session, storage, upload, name, settings=settings, **_limits(max_bytes, max_files))
    source = storage.path(upload.path)
    suffix = detect_archive(source)
    if suffix is None:
        _refuse_not_an_archive(session, storage, upload)
    archive = source.with_name("bundle" + suffix)  # open_bundle tells archive kinds by their suffix
    source.rename(archive)
    scene_id = uuid.uuid4()
    scene_dir = storage.scene_dir(scene_id)
    try:
        scene = _validated(session, upload, name, archive, scene_dir, scene_id, settings, _limits(max_bytes, max_files))
        scene.bundle_path = storage.rel(Path(scene.bundle_path))
        session.add(scene)
        session.commit()
    except BundleError as exc:
        session.rollback()
        storage.remove_tree(scene_dir)
        discard_upload(session, storage, upload)
        raise _invalid(exc) from exc
    except BaseException:
        # Not the bundle's fault (disk, database): undo, so that the same upload can be tried again.
        session.rollback()
        storage.remove_tree(scene_dir)
        archive.rename(source)
        crud.set_upload_state(session, upload.id, UploadState.CONSUMED, UploadState.COMPLETE)
        raise
    storage.remove_tree(archive.parent)  # the archive is extracted; its bytes are no longer needed
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
    session: Session,
    upload: Upload,
    name: str | None,
    archive: Path,
    workdir: Path,
    scene_id: uuid.UUID,
    settings: Settings | None,
    limits: dict[str, int],
) -> Scene:
    """Extract and check ``archive`` into ``workdir``; the scene's row (``bundle_path``: the bundle's folder)."""
    from panogs_core.io.bundle import open_bundle

    checks = bundle_limits(settings) if settings is not None else None
    bundle = open_bundle(archive, workdir=workdir, limits=checks, **limits)
    if name is None:  # the bundle's own name; a refusal keeps the upload, to retry with a "name"
        printable_text(bundle.name, 'scene.json: name (give a printable "name" in the request instead)')
    return Scene(
        id=scene_id,
        api_key_id=upload.api_key_id,
        name=(name or bundle.name)[:255],
        feature_dim=bundle.feature_dim,
        feature_space=bundle.feature_space,
        num_frames=len(bundle.frames),
        has_vocabulary=bundle.vocabulary is not None,
        has_ground_truth=bundle.has_ground_truth,
        bundle_path=str(bundle.root),
        bundle_sha256=upload.sha256,
        size_bytes=dir_size(workdir),
    )


def _create_from_objects(
    session: Session,
    storage: Storage,
    upload: Upload,
    name: str | None,
    *,
    settings: Settings | None,
    **limits: int,
) -> Scene:
    """:func:`create_scene` with an object storage: the archive is fetched into a scratch folder, extracted and
    checked there, and the bundle's files are stored under ``scenes/<id>/``; the scratch folder goes after."""
    head = b"".join(storage.objects.read_range(upload.path, 0, 512))
    suffix = archive_suffix(head)
    if suffix is None:
        _refuse_not_an_archive(session, storage, upload)
    scene_id = uuid.uuid4()
    prefix = storage.scene_prefix(scene_id)
    with storage.scratch("scene") as scratch:
        archive = scratch / ("bundle" + suffix)
        storage.objects.get_file(upload.path, archive)
        workdir = scratch / "scene"
        try:
            scene = _validated(session, upload, name, archive, workdir, scene_id, settings, limits)
            inside = Path(scene.bundle_path).relative_to(workdir).as_posix()
            scene.bundle_path = prefix + ("" if inside == "." else inside)
            storage.store_tree(workdir, prefix)
            session.add(scene)
            session.commit()
        except BundleError as exc:
            session.rollback()
            discard_upload(session, storage, upload)
            raise _invalid(exc) from exc
        except BaseException:
            session.rollback()
            storage.delete_prefix(prefix)
            crud.set_upload_state(session, upload.id, UploadState.CONSUMED, UploadState.COMPLETE)
            raise
    storage.delete_prefix(upload_folder(upload.path))  # extracted and stored: the archive's bytes are done with
    return scene
