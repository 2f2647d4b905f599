"""Safe extraction of uploaded bundle archives (``.zip``, ``.tar``, ``.tar.gz`` / ``.tgz``).

Nothing in an archive is trusted. Before anything is written every member is checked: its name must be
relative, stay inside the destination (no ``..``, no absolute or drive paths, no backslashes), be unique, and
name a regular file or folder (links and devices are refused), and fit the file system (no part over 255 bytes,
no name over 1,024); the member count and the total declared size must stay under the limits. While extracting,
bytes are counted again, because a zip's declared sizes can lie (archive bombs). Every problem found by the checks
is reported at once in one :class:`BundleError`, naming members by their names in the archive, never by where
they would be written. An error writing the destination that is not the archive's fault (a full disk) is
raised as the ``OSError`` it is, not as a problem of the bundle.
"""

from __future__ import annotations

import errno
import lzma
import re
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

from panogs_core.errors import BundleError

DEFAULT_MAX_BYTES = 32 * 1024**3  # uncompressed; a 2000-frame scene with dense 512-d maps fits
DEFAULT_MAX_FILES = 100_000  # five files per frame for 20k frames
_CHUNK = 1 << 20
_DRIVE = re.compile(r"^[A-Za-z]:")
MAX_NAME_PART_BYTES = 255  # NAME_MAX of Linux, macOS and Windows file systems
MAX_NAME_BYTES = 1024  # a whole member name; leaves room under PATH_MAX (4,096) for where it is extracted
_SHOWN_NAME_CHARS = 80  # a refused name of 10,000 characters is shown by its start
# Errors of writing a member that the member's name causes (the rest, such as a full disk, are the host's).
_NAME_ERRNOS = frozenset({errno.ENAMETOOLONG, errno.EEXIST, errno.EILSEQ, errno.EINVAL, errno.EISDIR, errno.ENOTDIR})
# Entries that archivers add beside the content folder; ignored when looking for a single top-level folder.
_ARCHIVER_LITTER = frozenset({"__MACOSX", ".DS_Store"})

_Opener = Callable[[str], IO[bytes]]  # opens a member, by its raw archive name, for reading
_Listing = Iterator[tuple[str, str | None, int, bool]]  # raw name, problem or None, declared size, is folder


@dataclass(frozen=True)
class _Member:
    name: str  # normalised relative posix path
    raw: str  # the name as stored in the archive
    is_dir: bool
    size: int  # declared uncompressed size in bytes


def is_archive(path: str | Path) -> bool:
    """True when ``path`` is a file with an archive extension this module extracts."""
    name = Path(path).name.lower()
    return Path(path).is_file() and name.endswith((".zip", ".tar", ".tar.gz", ".tgz"))


def extract_archive(
    archive: str | Path,
    dest: str | Path,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_files: int = DEFAULT_MAX_FILES,
) -> Path:
    """Check and extract an archive into ``dest``; return the bundle root inside it.

    The root is ``dest`` itself, or the single top-level folder of the archive when ``scene.json`` is not at
    the top (archives made by zipping a folder).

    Args:
        archive: ``.zip``, ``.tar``, ``.tar.gz`` or ``.tgz`` file.
        dest: Destination folder (created if missing; should be empty).
        max_bytes: Most uncompressed bytes allowed in total.
        max_files: Most members allowed (files and folders).

    Returns:
        The bundle root folder.

    Raises:
        BundleError: listing every unsafe member and limit breach, or the archive is corrupt or unreadable.
    """
    archive = Path(archive)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    source = archive.name
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as zf:
                members = _check_all(_zip_members(zf), max_bytes, max_files, source)
                _extract(members, zf.open, dest, max_bytes, source)
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive, mode="r:*") as tf:
                members = _check_all(_tar_members(tf), max_bytes, max_files, source)
                _extract(members, _tar_opener(tf), dest, max_bytes, source)
        else:
            raise BundleError([f"{source}: not a zip or tar archive"], source=source)
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError, RuntimeError, zlib.error, lzma.LZMAError) as exc:
        # Reading the archive only (writes raise _WriteError): RuntimeError is an encrypted zip member;
        # EOFError, OSError, zlib and lzma errors are truncated or corrupt compressed streams.
        raise BundleError([f"{source}: corrupt or unreadable archive ({_reason(exc)})"], source=source) from exc
    except _WriteError as exc:
        raise exc.error from None
    return find_bundle_root(dest)


class _WriteError(Exception):
    """Carries an OSError of writing the destination past the handler of the archive's read errors."""

    def __init__(self, error: OSError) -> None:
        super().__init__(str(error))
        self.error = error


def _reason(exc: BaseException) -> str:
    """An exception's reason without the file name an OSError carries (a path on the host)."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


def shown_name(raw: str) -> str:
    """A member name for a message: as stored, cut to its first characters when it is very long."""
    if len(raw) <= _SHOWN_NAME_CHARS:
        return raw
    return f"{raw[: _SHOWN_NAME_CHARS - 3]}... ({len(raw):,} characters)"


def find_bundle_root(folder: Path) -> Path:
    """``folder`` when it holds ``scene.json``, else its single top-level subfolder if that holds one."""
    if (folder / "scene.json").exists():
        return folder
    entries = [p for p in folder.iterdir() if p.name not in _ARCHIVER_LITTER]
    if len(entries) == 1 and entries[0].is_dir() and not entries[0].is_symlink():
        if (entries[0] / "scene.json").exists():
            return entries[0]
    return folder


# -- listing -------------------------------------------------------------------------------------------------


def _zip_members(zf: zipfile.ZipFile) -> _Listing:
    """(raw name, problem or None, declared size, is folder) per zip member."""
    for info in zf.infolist():
        # Unix file-type bits, when the archiver stored any (many store only permissions, or nothing).
        file_type = stat.S_IFMT(info.external_attr >> 16)
        problem = None
        if info.flag_bits & 0x1:
            problem = "encrypted member"
        elif file_type == stat.S_IFLNK:
            problem = "symbolic link"
        elif file_type not in (0, stat.S_IFREG, stat.S_IFDIR):
            problem = "not a regular file or folder"
        yield info.filename, problem, (0 if info.is_dir() else info.file_size), info.is_dir()


def _tar_members(tf: tarfile.TarFile) -> _Listing:
    """(raw name, problem or None, declared size, is folder) per tar member, read lazily header by header."""
    for info in tf:
        problem = None
        if info.issym():
            problem = f"symbolic link to {info.linkname!r}"
        elif info.islnk():
            problem = f"hard link to {info.linkname!r}"
        elif info.issparse() or not (info.isreg() or info.isdir()):
            problem = "not a regular file or folder (device, fifo or sparse)"
        yield info.name, problem, (info.size if info.isreg() else 0), info.isdir()


def _tar_opener(tf: tarfile.TarFile) -> _Opener:
    by_name = {info.name: info for info in tf.getmembers()}  # getmember() is a linear scan per call

    def open_member(name: str) -> IO[bytes]:
        fh = tf.extractfile(by_name[name])
        if fh is None:  # only regular files reach here, but tarfile's type says it may be None
            raise BundleError([f"{name}: cannot be read from the archive"])
        return fh

    return open_member


# -- checks --------------------------------------------------------------------------------------------------


def _check_all(listing: _Listing, max_bytes: int, max_files: int, source: str) -> list[_Member]:
    """Check every member; raise one BundleError with every problem, or return the members to extract.

    Listing stops as soon as a limit is passed: a bomb may hold millions of headers, and reading further (for
    a tar, seeking past a terabyte it declares) gains nothing.
    """
    problems: list[str] = []
    members: list[_Member] = []
    seen: set[str] = set()
    total = count = 0
    for raw, problem, size, is_dir in listing:
        count += 1
        if count > max_files:
            problems.append(f"{source}: more than {max_files} members (the limit)")
            break
        name, name_problem = _normalise(raw)
        if problem or name_problem:
            problems.append(f"{shown_name(raw)}: {problem or name_problem}")
            continue
        if not name:
            continue  # the archive's own root folder ("./"), written by `tar -C dir .`
        if name in seen:
            problems.append(f"{shown_name(raw)}: duplicate name in the archive")
            continue
        seen.add(name)
        total += size
        if total > max_bytes:
            problems.append(f"{source}: declared uncompressed size {total} bytes exceeds the limit of {max_bytes}")
            break
        members.append(_Member(name, raw, is_dir, size))
    problems += _file_folder_clashes(members)
    if problems:
        raise BundleError(problems, source=source)
    return members


def _normalise(raw: str) -> tuple[str, str | None]:
    """Normalised relative name, or a reason to refuse the raw name."""
    if not raw or "\x00" in raw:
        return "", "empty or NUL in name"
    if "\\" in raw:
        return "", "backslash in name (Windows path separators are not allowed)"
    if raw.startswith("/") or _DRIVE.match(raw):
        return "", "absolute path"
    parts = [p for p in PurePosixPath(raw).parts if p != "."]
    if ".." in parts:
        return "", "path leaves the bundle ('..')"
    name = "/".join(parts)  # "" for the root folder itself
    longest = max((len(p.encode("utf-8", "surrogateescape")) for p in parts), default=0)
    if longest > MAX_NAME_PART_BYTES:
        return "", f"a part of the name is {longest:,} bytes long, over the limit of {MAX_NAME_PART_BYTES}"
    if len(name.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES:
        return "", f"name over the limit of {MAX_NAME_BYTES:,} bytes"
    return name, None


def _file_folder_clashes(members: list[_Member]) -> list[str]:
    """Names used both as a file and as a folder prefix of another member."""
    files = {m.name for m in members if not m.is_dir}
    clashes = []
    for m in members:
        parts = m.name.split("/")
        for i in range(1, len(parts)):
            prefix = "/".join(parts[:i])
            if prefix in files:
                clashes.append(f"{shown_name(m.name)}: {shown_name(prefix)!r} is both a file and a folder")
                break
    return clashes


# -- extraction ----------------------------------------------------------------------------------------------


def _extract(members: list[_Member], open_member: _Opener, dest: Path, max_bytes: int, source: str) -> None:
    """Write every member below ``dest``, counting the bytes actually produced against ``max_bytes``."""
    total = 0
    for m in members:
        target = dest.joinpath(*m.name.split("/"))
        if m.is_dir:
            with _writing(m, source):
                target.mkdir(parents=True, exist_ok=True)
            continue
        with _writing(m, source):
            target.parent.mkdir(parents=True, exist_ok=True)
            out = target.open("xb")
        with out, open_member(m.raw) as src:
            while chunk := src.read(_CHUNK):  # reading: its errors are the archive's
                total += len(chunk)
                if total > max_bytes:
                    raise BundleError(
                        [f"{shown_name(m.name)}: archive expands past the limit of {max_bytes} bytes"], source=source
                    )
                with _writing(m, source):
                    out.write(chunk)


@contextmanager
def _writing(member: _Member, source: str) -> Iterator[None]:
    """Around one write to the destination: an error the member's name causes is a problem of the bundle, named
    by the member; any other (disk full, permissions) is the host's and passes on as :class:`_WriteError`."""
    try:
        yield
    except OSError as exc:
        if exc.errno in _NAME_ERRNOS:
            problem = f"{shown_name(member.name)}: cannot be extracted under this name ({_reason(exc)})"
            raise BundleError([problem], source=source) from None
        raise _WriteError(exc) from exc
