"""An upload's archive on its way into a scene's bundle, on either backend.

- **Local backend**: the upload's file is renamed to ``bundle<suffix>`` beside itself (the core tells archive
  kinds by their suffix) and extracted into ``scenes/<id>/`` in place.
- **Object storage**: the archive is fetched into a scratch folder, extracted there, and the bundle's files are
  stored under ``scenes/<id>/``; the scratch folder goes after.

The caller validates what lands in :attr:`Extraction.workdir` and then says how it ended: :meth:`keep` (valid: the
bundle is stored), :meth:`refuse` (the bundle broke the format: nothing of the extraction stays), :meth:`undo`
(not the bundle's fault: everything as before, the upload to be tried again), :meth:`done` (the scene is
recorded: the archive's bytes go).
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Protocol

from service.storage.files import archive_suffix, detect_archive, upload_folder
from service.storage.objects import ObjectStorage


class ExtractionStore(Protocol):
    """What an extraction needs of ``service.storage.Storage`` (named here so that this module imports none of it)."""

    @property
    def objects(self) -> ObjectStorage: ...

    def path(self, rel: str) -> Path: ...

    def rel(self, path: Path) -> str: ...

    def scene_dir(self, scene_id: uuid.UUID) -> Path: ...

    def scene_prefix(self, scene_id: uuid.UUID) -> str: ...

    def remove_tree(self, path: Path) -> None: ...

    def store_tree(self, folder: Path, prefix: str) -> int: ...

    def delete_prefix(self, prefix: str) -> int: ...

    def scratch(self, what: str) -> AbstractContextManager[Path]: ...


class Extraction:
    """The local backend's: the archive and the bundle's folder are the stored files themselves."""

    def __init__(self, storage: ExtractionStore, archive: Path, workdir: Path, source: Path) -> None:
        self.storage = storage
        self.archive = archive
        self.workdir = workdir
        self._source = source

    def bundle_key(self, bundle_root: Path) -> str:
        """The ``bundle_path`` a scene's row stores for the bundle at ``bundle_root`` (inside :attr:`workdir`)."""
        return self.storage.rel(bundle_root)

    def keep(self) -> None:
        """The bundle is valid: it is stored where the scene's row points (here: it is already)."""

    def refuse(self) -> None:
        """The bundle was refused: remove what was extracted."""
        self.storage.remove_tree(self.workdir)

    def undo(self) -> None:
        """Not the bundle's fault: remove what was extracted and give the upload its bytes back."""
        self.storage.remove_tree(self.workdir)
        self.archive.rename(self._source)

    def done(self) -> None:
        """The scene is recorded: the archive's bytes are no longer needed."""
        self.storage.remove_tree(self.archive.parent)


class FetchedExtraction(Extraction):
    """Object storage's: the archive and the extraction live in a scratch folder; the bundle is stored after."""

    def __init__(self, storage: ExtractionStore, archive: Path, workdir: Path, upload_key: str, prefix: str) -> None:
        super().__init__(storage, archive, workdir, archive)
        self._upload_key = upload_key
        self._prefix = prefix

    def bundle_key(self, bundle_root: Path) -> str:
        inside = bundle_root.relative_to(self.workdir).as_posix()
        return self._prefix + ("" if inside == "." else inside)

    def keep(self) -> None:
        self.storage.store_tree(self.workdir, self._prefix)

    def refuse(self) -> None:
        """Nothing to remove: the scratch folder goes with the extraction."""

    def undo(self) -> None:
        self.storage.delete_prefix(self._prefix)

    def done(self) -> None:
        self.storage.delete_prefix(upload_folder(self._upload_key))


@contextmanager
def open_extraction(
    storage: ExtractionStore, in_place: bool, upload_key: str, scene_id: uuid.UUID
) -> Iterator[Extraction | None]:
    """The extraction of the upload at ``upload_key`` into scene ``scene_id``; None when the upload is not an archive
    (by its first bytes)."""
    if in_place:
        source = storage.path(upload_key)
        suffix = detect_archive(source)
        if suffix is None:
            yield None
            return
        archive = source.with_name("bundle" + suffix)
        source.rename(archive)
        yield Extraction(storage, archive, storage.scene_dir(scene_id), source)
        return
    suffix = archive_suffix(b"".join(storage.objects.read_range(upload_key, 0, 512)))
    if suffix is None:
        yield None
        return
    with storage.scratch("scene") as scratch:
        archive = scratch / ("bundle" + suffix)
        storage.objects.get_file(upload_key, archive)
        yield FetchedExtraction(storage, archive, scratch / "scene", upload_key, storage.scene_prefix(scene_id))
