"""The header of a ``.npy`` array (alone, or a member of an ``.npz``), read and bounded before any data is read.

numpy's header reader accepts any Python integers as a shape: negative sizes, ``True``, or ``10**30``. Sizes are
therefore computed here with Python integers (``numpy.prod(shape, dtype=int64)`` wraps: a shape of
``(10**19, 6, 8)`` multiplies to 0 bytes and would pass for an empty, complete file), and every check compares
the declared size with what is really there (the file's bytes after its header, or the member's size in the zip)
before anything is allocated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import IO, Any

import numpy as np

from panogs_core.errors import InputError

__all__ = ["MAX_DIM", "MAX_NDIM", "NpyHeader", "read_npy_header"]

MAX_NDIM = 32  # numpy itself allows 64; no array of the formats here has more than 3
MAX_DIM = 2**63 - 1  # numpy's own ceiling (intp); also keeps every product printable (Python refuses to print
# an integer of more than 4,300 digits)


@dataclass(frozen=True)
class NpyHeader:
    """What a ``.npy`` header declares.

    Attributes:
        shape: Sizes, each a Python int >= 0.
        fortran_order: The data is in Fortran (column-major) order.
        dtype: Element type (never one holding Python objects: those are refused when read).
        offset: Bytes of the magic string and header; the data starts there.
    """

    shape: tuple[int, ...]
    fortran_order: bool
    dtype: np.dtype[Any]
    offset: int

    @property
    def count(self) -> int:
        """Elements declared (exact, never wrapped)."""
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        """Data bytes declared (exact, never wrapped)."""
        return self.count * self.dtype.itemsize

    def size_problem(self, available: int) -> str | None:
        """Why ``available`` data bytes do not hold the declared array, or None when they match exactly."""
        if self.nbytes == available:
            return None
        return (
            f"shape {self.shape} of {self.dtype} declares {self.nbytes:,} data bytes, the file holds {available:,} "
            "after its header (truncated, or a false shape)"
        )


def read_npy_header(fh: IO[bytes], name: str) -> NpyHeader:
    """Read the magic string and header of a ``.npy`` stream, leaving ``fh`` at the first data byte.

    Args:
        fh: Binary stream at the start of the array.
        name: How messages name the file (bundle-relative, e.g. ``features/000000.npy``).

    Raises:
        InputError: naming ``name``, if the magic or header is malformed, the dtype holds Python objects
            (pickles), or the shape is not a tuple of at most :data:`MAX_NDIM` integers >= 0.
    """
    start = fh.tell()
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):  # 3.0 only changes the header's text encoding
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except (ValueError, SyntaxError, TypeError, OverflowError, MemoryError, RecursionError) as exc:
        raise InputError(f"{name}: not a valid .npy file ({exc})") from exc
    if dtype.hasobject:
        raise InputError(f"{name}: holds pickled Python objects (dtype {dtype}), expected a plain numeric array")
    if len(shape) > MAX_NDIM or any(
        isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= MAX_DIM for s in shape
    ):
        raise InputError(f"{name}: shape {_short(shape)}, expected at most {MAX_NDIM} integer sizes in [0, 2**63)")
    return NpyHeader(tuple(int(s) for s in shape), bool(fortran), dtype, fh.tell() - start)


def _is_size(value: Any) -> bool:
    """A dimension numpy can hold: an int (not a bool, which is one) in [0, MAX_DIM]."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_DIM


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."
