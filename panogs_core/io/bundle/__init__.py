"""The scene bundle, format ``panogs-scene/1`` (docs/scene_format.md), in one place: :func:`open_bundle` (an archive
extracted safely, then validated), the rules (``format``), the reader (``reader.Bundle``), the validation
(``validation``), the writer (``writer.BundleWriter``) and archives (``archive``).

``open_bundle(path)`` accepts a folder or a ``.zip`` / ``.tar`` / ``.tar.gz`` archive (safely extracted to a
temporary folder first), validates every rule of the format at once and raises :class:`BundleError` with one
line per problem. The returned :class:`Bundle` reads frames one at a time: nothing large is held in memory.
"""

from __future__ import annotations

import shutil
import tempfile
import weakref
from pathlib import Path

from panogs_core.errors import BundleError
from panogs_core.io.bundle.archive import DEFAULT_MAX_BYTES, DEFAULT_MAX_FILES, extract_archive, is_archive
from panogs_core.io.bundle.format import FORMAT_ID, BundleLimits
from panogs_core.io.bundle.problems import CpuBudget
from panogs_core.io.bundle.reader import Bundle
from panogs_core.io.bundle.validation import relative_to_root, validate

__all__ = ["FORMAT_ID", "Bundle", "BundleLimits", "open_bundle"]


def open_bundle(
    path: str | Path,
    *,
    workdir: str | Path | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_files: int = DEFAULT_MAX_FILES,
    limits: BundleLimits | None = None,
) -> Bundle:
    """Open and validate a bundle folder or archive.

    Args:
        path: Bundle folder, or ``.zip`` / ``.tar`` / ``.tar.gz`` / ``.tgz``.
        workdir: Parent folder for the extraction of an archive; a fresh subfolder is made in it and kept (the
            caller owns ``workdir``). Without it, a temporary folder is used and removed when the returned
            ``Bundle`` is garbage collected (or at once when validation fails).
        max_bytes: Most uncompressed bytes an archive may expand to.
        max_files: Most members an archive may hold.
        limits: What the files may declare (default: :class:`BundleLimits()`).

    Returns:
        The validated bundle.

    Raises:
        BundleError: listing every problem found, each naming its file relative to the bundle.
    """
    path = Path(path)
    limits = limits or BundleLimits()
    budget = CpuBudget(limits.max_cpu_s)  # the extraction counts in the budget too
    if path.is_dir():
        return validate(path, limits=limits, budget=budget)
    if not path.exists():
        raise BundleError([f"{path.name}: does not exist"], source=path.name)
    if not is_archive(path):
        raise BundleError([f"{path.name}: not a folder or a .zip/.tar/.tar.gz archive"], source=path.name)
    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)
    dest = Path(tempfile.mkdtemp(prefix="bundle-", dir=workdir))
    try:
        root = extract_archive(path, dest, max_bytes=max_bytes, max_files=max_files)
        bundle = validate(root, source=path.name, limits=limits, budget=budget)
    except BundleError as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise BundleError(relative_to_root(exc.problems, dest), source=exc.source) from exc
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    if workdir is None:
        weakref.finalize(bundle, shutil.rmtree, str(dest), True)
    return bundle
