"""Unpack Record3D's ``.r3d`` archive into the layout of its EXR + JPG export, for :mod:`record3d` to read.

An ``.r3d`` file is a zip archive::

    metadata            JSON: K (column-major), w, h, dw, dh, poses ([qx, qy, qz, qw, tx, ty, tz] per frame), ...
    rgbd/<n>.jpg        colour
    rgbd/<n>.depth      LZFSE-compressed float32 depth in metres at dw x dh
    rgbd/<n>.conf       LZFSE-compressed uint8 ARKit confidence (optional)

Only members of exactly these names are extracted, each to a path built here (never the member's own name), so an
archive cannot write outside the temporary folder. The compressed files are copied as they are and decoded per
frame by :func:`record3d.read_lzfse`, so one damaged frame is dropped and named like the others.
"""

from __future__ import annotations

import re
import shutil
import tempfile
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from panogs_core.errors import InputError

_MEMBER = re.compile(r"^rgbd/(\d+)\.(jpg|depth|conf)$")
_TARGET = {"jpg": "rgb", "depth": "depth", "conf": "conf"}
MAX_METADATA_BYTES = 64 * 2**20  # the bundle's JSON limit (docs/scene_format.md §5); poses of ~1M frames fit


@contextmanager
def unpacked_r3d(archive: Path) -> Iterator[Path]:
    """A temporary folder holding ``metadata.json``, ``rgb/<n>.jpg``, ``depth/<n>.depth``, ``conf/<n>.conf``.

    Raises:
        InputError: naming the archive, if it is not a zip file or has no ``metadata`` member.
    """
    with tempfile.TemporaryDirectory(prefix="panogs-r3d-") as tmp:
        root = Path(tmp)
        for sub in _TARGET.values():
            (root / sub).mkdir()
        try:
            with zipfile.ZipFile(archive) as zf:
                names = set(zf.namelist())
                if "metadata" not in names:
                    raise InputError(f"import record3d: {archive}: no 'metadata' member (not a Record3D .r3d file?)")
                if zf.getinfo("metadata").file_size > MAX_METADATA_BYTES:
                    raise InputError(f"import record3d: {archive}: metadata larger than {MAX_METADATA_BYTES} bytes")
                _extract(zf, "metadata", root / "metadata.json")
                for name in names:
                    match = _MEMBER.match(name)
                    if match:
                        index, kind = match.groups()
                        _extract(zf, name, root / _TARGET[kind] / f"{int(index)}.{kind}")
        except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
            raise InputError(f"import record3d: {archive}: not a readable .r3d (zip) archive ({exc})") from exc
        yield root


def _extract(zf: zipfile.ZipFile, name: str, target: Path) -> None:
    with zf.open(name) as src, target.open("wb") as dst:
        shutil.copyfileobj(src, dst)
