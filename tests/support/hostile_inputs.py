"""Hostile inputs for the boundary tests of the service (``tests/service/test_hostile.py``).

Hypothesis strategies draw *descriptions* of bad input (a damage to a bundle, a hostile JSON value, a header);
plain functions turn a description into bytes: deep JSON, integers with thousands of digits, PNGs whose
headers declare huge sizes, archives with unsafe member names or links. The builders are deterministic and
write nothing to disk; the strategies draw only their arguments, so that a failing example reads as what it
did (``HugeInt(file='scene.json', field=('camera', 'width'), digits=5000)``).

Host paths drawn here (``/etc/passwd`` ...) are only ever sent as data: a request or a bundle that names one
must be refused without the path being opened.
"""

from __future__ import annotations

import io
import json
import re
import stat
import struct
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from hypothesis import strategies as st

# Paths of the host that no request may make the service open (and that no answer may name).
HOST_PATHS = (
    "/etc/passwd",
    "/etc/shadow",
    "/etc/hostname",
    "/root/.ssh/id_rsa",
    "/proc/self/environ",
    "/proc/self/cmdline",
    "/dev/zero",
    "/dev/urandom",
    "/tmp",
    "../../../../../../etc/passwd",
    "./../../etc/hosts",
    "file:///etc/passwd",
    "~/.bash_history",
    "C:\\Windows\\win.ini",
    "\\\\host\\share\\file",
)
# Absolute paths of the host in an answer: the roots of a Linux host's file system.
_HOST_PATH_IN_TEXT = re.compile(r"(?<![\w.:/-])/(?:etc|root|tmp|home|proc|dev|var|usr|opt|srv|work|mnt|run)(?:/|\b)")
TRACEBACK_MARKERS = ("Traceback (most recent call last)", 'File "', '.py", line ')


def host_path_leaks(text: str, *, known: Sequence[str] = (), sent: Sequence[str] = ()) -> list[str]:
    """Absolute host paths in ``text``: the ``known`` ones (the storage root, the test's folder) anywhere, and any
    path under a root of the file system. What the request itself ``sent`` may be echoed and is removed first."""
    for echoed in sorted(sent, key=len, reverse=True):
        if echoed:
            text = text.replace(echoed, "<sent>")
            text = text.replace(json.dumps(echoed)[1:-1], "<sent>")  # as it appears inside a JSON string
    found = [k for k in known if k and k in text]
    found += [m.group(0) for m in _HOST_PATH_IN_TEXT.finditer(text)]
    return found


def traceback_markers(text: str) -> list[str]:
    """The markers of a Python traceback found in ``text``."""
    return [m for m in TRACEBACK_MARKERS if m in text]


# -- JSON -----------------------------------------------------------------------------------------------------


def nested_json(depth: int, *, bracket: str = "[", leaf: str = "1") -> str:
    """``depth`` nested arrays (``[``) or objects (``{``) around ``leaf``, as JSON text (no recursion here)."""
    if bracket == "[":
        return "[" * depth + leaf + "]" * depth
    return '{"a":' * depth + leaf + "}" * depth


def huge_integer(digits: int) -> str:
    """A JSON integer of ``digits`` digits (Python refuses to convert more than 4300 by default)."""
    return "9" * digits


@dataclass(frozen=True)
class JsonText:
    """A JSON document given as text, to send as a body or to write as a bundle's JSON file."""

    text: str
    what: str

    def __repr__(self) -> str:  # hypothesis prints the drawn examples; a 100 kB text would hide the point
        return f"JsonText({self.what})"


def _with_raw(doc: Any, raw: str) -> str:
    """``doc`` as JSON with the string ``"@RAW@"`` replaced by raw JSON text (deep nesting, huge numbers)."""
    return json.dumps(doc).replace('"@RAW@"', raw, 1)


def raw_json_values() -> st.SearchStrategy[tuple[str, str]]:
    """(raw JSON text, what it is) for one value: very deep nesting, a huge integer, a huge or tiny float,
    NaN / Infinity (which Python's reader accepts), or a plain hostile value."""
    deep = st.builds(
        lambda depth, bracket: (nested_json(depth, bracket=bracket), f"nested {depth} deep in {bracket}"),
        st.sampled_from([64, 200, 500, 1000, 3000, 20_000, 100_000]),
        st.sampled_from(["[", "{"]),
    )
    big = st.builds(
        lambda digits, sign: (sign + huge_integer(digits), f"integer of {digits} digits"),
        st.sampled_from([20, 400, 4301, 5000, 50_000]),
        st.sampled_from(["", "-"]),
    )
    floats = st.sampled_from(
        [("1e999", "1e999"), ("-1e999", "-1e999"), ("NaN", "NaN"), ("Infinity", "Infinity"), ("5e-324", "5e-324")]
    )
    plain = hostile_json_values().map(lambda v: (json.dumps(v), f"value {json.dumps(v)[:60]}"))
    return st.one_of(deep, big, floats, plain)


def hostile_json_values(extra_strings: Sequence[str] = ()) -> st.SearchStrategy[Any]:
    """Ordinary JSON values of the wrong kind: host paths, NUL and control characters, long strings, big
    numbers, and small nested lists and objects of them."""
    strings = st.one_of(
        st.sampled_from([*HOST_PATHS, *extra_strings, "", " ", "\x00", "a\x00b", "\ud7ff\u202e", "%s%n", "${HOME}"]),
        st.text(max_size=40),
        st.integers(256, 5000).map(lambda n: "x" * n),
    )
    scalars = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(2**70), 2**70),
        st.floats(allow_nan=False, allow_infinity=False),
        strings,
    )
    return st.recursive(
        scalars,
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
        max_leaves=12,
    )


# -- images ---------------------------------------------------------------------------------------------------


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # PNG colour type -> channels


def _zeros_zlib(total: int) -> bytes:
    """A zlib stream of ``total`` zero bytes, built without compressing them all: blocks ended by a full
    flush compress to the same bytes each time, so one block is compressed and repeated."""
    block = 1 << 20
    full, rest = divmod(total, block)
    compressor = zlib.compressobj(9)
    head = compressor.compress(bytes(block)) + compressor.flush(zlib.Z_FULL_FLUSH) if full else b""
    repeat = compressor.compress(bytes(block)) + compressor.flush(zlib.Z_FULL_FLUSH) if full > 1 else b""
    tail = compressor.compress(bytes(rest)) + compressor.flush(zlib.Z_FULL_FLUSH)
    if not full:
        head, tail = tail, b""
    checksum = 1
    zero_block = bytes(block)
    for _ in range(full):
        checksum = zlib.adler32(zero_block, checksum)
    checksum = zlib.adler32(bytes(rest), checksum)
    # An empty final fixed-Huffman block ends the deflate stream; the Adler-32 of every byte follows.
    return head + repeat * max(0, full - 1) + tail + b"\x03\x00" + struct.pack(">I", checksum)


def png(width: int, height: int, *, bit_depth: int = 8, color_type: int = 0, complete: bool = True) -> bytes:
    """A black PNG whose header declares ``width`` x ``height``; with ``complete=False`` the data stops halfway
    (the header still declares the full size). A complete one is built in milliseconds at any size."""
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0)
    row = 1 + width * _CHANNELS[color_type] * bit_depth // 8  # a filter byte, then the samples
    if complete:
        pixels = _zeros_zlib(row * height)
    else:  # the first half of the data at most, and a stream that never ends: a decoder must fail
        compressor = zlib.compressobj(9)
        pixels = compressor.compress(bytes(min(row * height // 2, 1 << 16))) + compressor.flush(zlib.Z_SYNC_FLUSH)
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", pixels) + _png_chunk(b"IEND", b"")


# -- archives -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Link:
    """An archive member that is a link (``hard`` only in tar archives) to ``target``."""

    target: str
    hard: bool = False


Members = dict[str, "bytes | Link"]


def read_members(root: Path) -> dict[str, bytes]:
    """Every file under a bundle folder, by its posix path relative to the folder."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def pack_members(members: Mapping[str, bytes | Link], kind: str) -> bytes:
    """The members as a ``zip``, ``tar`` or ``tar.gz`` archive, names as given (unsafe ones included)."""
    buffer = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, data in members.items():
                zinfo = zipfile.ZipInfo(name)
                zinfo.compress_type = zipfile.ZIP_DEFLATED
                if isinstance(data, Link):  # zip has no hard links: both become symbolic links
                    zinfo.external_attr = (stat.S_IFLNK | 0o777) << 16
                    zf.writestr(zinfo, data.target)
                else:
                    zinfo.external_attr = (stat.S_IFREG | 0o644) << 16
                    zf.writestr(zinfo, data)
        return buffer.getvalue()
    with tarfile.open(fileobj=buffer, mode="w:gz" if kind == "tar.gz" else "w", format=tarfile.PAX_FORMAT) as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            if isinstance(data, Link):
                info.type = tarfile.LNKTYPE if data.hard else tarfile.SYMTYPE
                info.linkname = data.target
                tf.addfile(info)
            else:
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


# -- damages to a valid bundle ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class BadBundle:
    """An archive of a damaged bundle: its bytes, what was done, and the strings of its own that a refusal may
    name (member names, link targets)."""

    data: bytes
    what: str
    echoes: tuple[str, ...] = ()
    file: str | None = None  # the file a refusal must name, where one is to blame


@dataclass(frozen=True)
class Damage:
    """A way to break a valid bundle; ``apply`` takes its members (path -> bytes) and returns the archive."""

    kind: str = field(default="zip", kw_only=True)  # archive format

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        """Change ``members`` in place; returns (echoes, the file to blame)."""
        raise NotImplementedError

    def apply(self, valid: Mapping[str, bytes]) -> BadBundle:
        members: Members = dict(valid)
        echoes, blamed = self.edit(members)
        return BadBundle(pack_members(members, self.kind), repr(self), echoes, blamed)


def _set_field(doc: Any, path: Sequence[str | int], value: Any) -> None:
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


@dataclass(frozen=True)
class RawField(Damage):
    """A field of ``scene.json`` or ``vocabulary.json`` set to raw JSON (deep nesting, a huge integer, NaN...)."""

    file: str = "scene.json"
    path: tuple[str | int, ...] = ("name",)
    raw: str = "1"
    label: str = ""

    def __repr__(self) -> str:
        return f"RawField({self.kind}: {self.file} {'.'.join(map(str, self.path))} = {self.label or self.raw[:40]})"

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        doc = json.loads(members[self.file])  # type: ignore[arg-type]
        _set_field(doc, self.path, "@RAW@")
        members[self.file] = _with_raw(doc, self.raw).encode()
        return (), self.file


@dataclass(frozen=True)
class WholeFile(Damage):
    """A bundle file replaced by other bytes (a deep JSON document, a PLY or .npy header with a huge count)."""

    file: str = "scene.json"
    content: bytes = b""
    label: str = ""

    def __repr__(self) -> str:
        return f"WholeFile({self.kind}: {self.file} = {self.label})"

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        members[self.file] = self.content
        return (), self.file


@dataclass(frozen=True)
class WrongType(Damage):
    """A field of ``scene.json`` or ``vocabulary.json`` given a value of the wrong kind."""

    file: str = "scene.json"
    path: tuple[str | int, ...] = ("camera",)
    value: Any = None

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        doc = json.loads(members[self.file])  # type: ignore[arg-type]
        _set_field(doc, self.path, self.value)
        members[self.file] = json.dumps(doc).encode()
        strings = tuple(s for s in _strings_in(self.value) if s)
        return strings, self.file


def _strings_in(value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, list):
        return [s for v in value for s in _strings_in(v)]
    if isinstance(value, dict):
        return [s for k, v in value.items() for s in (k, *_strings_in(v))]
    return []


@dataclass(frozen=True)
class Missing(Damage):
    """A file the manifest needs is absent."""

    file: str = "depth/000000.png"

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        members.pop(self.file, None)
        return (), self.file


@dataclass(frozen=True)
class ExtraMember(Damage):
    """One more member with an unsafe name (traversal, absolute, too long, too deep) or that is a link."""

    name: str = "extra.bin"
    link: Link | None = None

    def __repr__(self) -> str:
        name = self.name if len(self.name) <= 60 else f"{self.name[:30]}...({len(self.name)} chars)"
        return f"ExtraMember({self.kind}: {name!r}{f' -> {self.link}' if self.link else ''})"

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        members[self.name] = self.link if self.link is not None else b"hostile\n"
        echoes = (self.name, *(self.link.target for _ in [0] if self.link is not None))
        return echoes, None


@dataclass(frozen=True)
class Image(Damage):
    """A frame image replaced by a PNG whose header declares ``width`` x ``height``."""

    file: str = "masks/000000.png"
    width: int = 1
    height: int = 1
    bit_depth: int = 8
    color_type: int = 0
    complete: bool = False

    def edit(self, members: Members) -> tuple[tuple[str, ...], str | None]:
        members[self.file] = png(
            self.width, self.height, bit_depth=self.bit_depth, color_type=self.color_type, complete=self.complete
        )
        return (), self.file


# Files of the tiny test bundle's frames that the manifest names (colour is JPEG there; a PNG's bytes under the
# .jpg name are decoded by content, as a real decoder does).
FRAME_FILES = ("depth/000000.png", "color/000001.jpg", "masks/000000.png")
ARCHIVE_KINDS = st.sampled_from(["zip", "tar", "tar.gz"])

# Fields of scene.json and vocabulary.json, by path, that a wrong type or a raw value can replace.
SCENE_FIELDS: tuple[tuple[str | int, ...], ...] = (
    ("format",),
    ("name",),
    ("camera",),
    ("camera", "width"),
    ("camera", "height"),
    ("camera", "fx"),
    ("camera", "cx"),
    ("depth_scale",),
    ("features",),
    ("features", "dim"),
    ("features", "space"),
    ("frames",),
    ("frames", 0),
    ("frames", 0, "id"),
    ("frames", 0, "pose"),
    ("frames", 0, "pose", 0),
    ("frames", 0, "pose", 0, 3),
    ("frames", 0, "depth"),
    ("frames", 0, "color"),
    ("frames", 0, "features"),
    ("frames", 1, "masks"),
)
VOCABULARY_FIELDS: tuple[tuple[str | int, ...], ...] = (
    ("classes",),
    ("classes", 0),
    ("classes", 0, "name"),
    ("classes", 1, "kind"),
    ("embeddings",),
)


def _fields() -> st.SearchStrategy[tuple[str, tuple[str | int, ...]]]:
    return st.one_of(
        st.sampled_from(SCENE_FIELDS).map(lambda p: ("scene.json", p)),
        st.sampled_from(VOCABULARY_FIELDS).map(lambda p: ("vocabulary.json", p)),
    )


def _huge_header_sizes() -> st.SearchStrategy[tuple[int, int]]:
    """Sizes a PNG header may declare: small, or so large that no decoder should allocate them (over 2**30
    pixels). Sizes in between would make the code under test allocate gigabytes before the decoder fails."""
    small = st.tuples(st.integers(1, 2048), st.integers(1, 2048))
    huge = st.tuples(st.integers(2**15 + 1, 2**31 - 1), st.integers(2**15 + 1, 2**31 - 1))
    return st.one_of(small, huge)


def _link_targets(extra: Sequence[str]) -> st.SearchStrategy[str]:
    return st.sampled_from([*HOST_PATHS[:6], "../../../etc/passwd", "scene.json", "../uploads", *extra])


def _unsafe_names() -> st.SearchStrategy[str]:
    traversal = st.sampled_from(
        ["../escape.txt", "../../../../tmp/escape.txt", "/etc/cron.d/escape", "a/../../escape.txt", "./../x",
         "C:/escape.txt", "a\\..\\..\\escape.txt", "color/../../escape.png", "//server/share/x"]
    )  # fmt: skip
    too_long = st.integers(256, 2000).map(lambda n: "color/" + "n" * n + ".png")
    too_deep = st.integers(2100, 3000).map(lambda n: "d/" * n + "f.bin")  # past PATH_MAX (4096) wherever it lands
    return st.one_of(traversal, too_long, too_deep)


def _plain_files() -> st.SearchStrategy[WholeFile]:
    """Non-JSON bundle files whose headers declare absurd counts or shapes."""
    ply = st.sampled_from([5000, 50_000]).map(
        lambda digits: WholeFile(
            file="geometry.ply",
            content=(
                f"ply\nformat binary_little_endian 1.0\nelement vertex {huge_integer(digits)}\n"
                "property float x\nproperty float y\nproperty float z\nend_header\n"
            ).encode(),
            label=f"vertex count of {digits} digits",
        )
    )
    npy = st.sampled_from([10**19, 10**30, 2**63 - 1, 2**62]).map(
        lambda n: WholeFile(file="features/000000.npy", content=npy_header((n, 6, 8)), label=f"npy shape ({n}, 6, 8)")
    )
    return st.one_of(ply, npy)


def npy_header(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    """A version 1.0 ``.npy`` header declaring ``shape`` (no data follows)."""
    text = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape!r}, }}"
    text += " " * (63 - (len(text) + 10) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1")


def damages(link_targets: Sequence[str] = ()) -> st.SearchStrategy[Damage]:
    """Every kind of damage, each in every archive format. ``link_targets`` adds paths of the test's own (another
    tenant's files) to the targets of link members."""
    raw = st.builds(
        lambda f, value, kind: RawField(file=f[0], path=f[1], raw=value[0], label=value[1], kind=kind),
        _fields(),
        raw_json_values(),
        ARCHIVE_KINDS,
    )
    whole_json = st.builds(
        lambda name, depth, bracket, kind: WholeFile(
            file=name, content=nested_json(depth, bracket=bracket).encode(), label=f"nested {depth} deep", kind=kind
        ),
        st.sampled_from(["scene.json", "vocabulary.json"]),
        st.sampled_from([1000, 5000, 100_000]),
        st.sampled_from(["[", "{"]),
        ARCHIVE_KINDS,
    )
    wrong = st.builds(
        lambda f, value, kind: WrongType(file=f[0], path=f[1], value=value, kind=kind),
        _fields(),
        hostile_json_values(),
        ARCHIVE_KINDS,
    )
    missing = st.builds(
        lambda name, kind: Missing(file=name, kind=kind),
        st.sampled_from(["scene.json", *FRAME_FILES, "features/000001.npy", "vocabulary.npy"]),
        ARCHIVE_KINDS,
    )
    unsafe = st.builds(lambda name, kind: ExtraMember(name=name, kind=kind), _unsafe_names(), ARCHIVE_KINDS)
    links = st.builds(
        lambda name, target, hard, kind: ExtraMember(name=name, link=Link(target, hard and kind != "zip"), kind=kind),
        st.sampled_from(["passwd", "color/000002.png", "vocabulary.json.bak", "gt"]),
        _link_targets(link_targets),
        st.booleans(),
        ARCHIVE_KINDS,
    )
    images = st.builds(
        lambda name, size, depth, ctype, kind: Image(
            file=name, width=size[0], height=size[1], bit_depth=depth, color_type=ctype, complete=False, kind=kind
        ),
        st.sampled_from(FRAME_FILES),
        _huge_header_sizes(),
        st.sampled_from([8, 16]),
        st.sampled_from(list(_CHANNELS)),
        ARCHIVE_KINDS,
    )
    plain = st.builds(lambda d, kind: replace(d, kind=kind), _plain_files(), ARCHIVE_KINDS)
    return st.one_of(raw, whole_json, wrong, missing, unsafe, links, images, plain)


# -- request bodies and headers ---------------------------------------------------------------------------------


def hostile_body(fill: Callable[[str], str], slots: Sequence[str]) -> st.SearchStrategy[JsonText]:
    """A JSON body: a template (with ``"@RAW@"`` where a slot goes) filled with one raw hostile value."""
    return st.builds(
        lambda slot, value: JsonText(fill(slot).replace('"@RAW@"', value[0], 1), f"{slot} = {value[1]}"),
        st.sampled_from(list(slots)),
        raw_json_values(),
    )


def header_values() -> st.SearchStrategy[str]:
    """Values of a numeric or structured header: negative, huge, not numbers, spaces, separators."""
    return st.one_of(
        st.sampled_from(
            [
                "-1",
                "0",
                "1e3",
                "0x10",
                " 7",
                "1,2",
                "",
                "NaN",
                "Infinity",
                "9" * 20,
                "9" * 5000,
                "10 10",
                "sha256",
                "sha256 !!!",
                "md5 AAAA",
                "filename",
                "filename ,",
                ",,,",
            ]
        ),
        st.integers(-(2**70), 2**70).map(str),
        st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=40),
    )
