"""``.npz`` files written without copying their arrays: the stage checkpoints (``save``) and the run's arrays.

``numpy.savez`` writes each array into its zip member through 16 MB chunks copied out of the array (its writer
copies whenever the target is not a plain file, and a zip member is not): two transient 16 MB buffers per array,
and at ScanNet size 40 MB more at the peak when a checkpoint is written beside the next stage (docs/benchmarks.md,
"Speed at ScanNet size, fourth pass"). Here each array goes to the member as one buffer, straight from its memory.
The file is an ordinary ``.npz`` (stored, not compressed; ``.npy`` headers of format 1.0, or 2.0 when the header
is too long): ``numpy.load`` reads it.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import IO

import numpy as np

__all__ = ["save_npz"]


def save_npz(target: str | Path | IO[bytes], **arrays: np.ndarray) -> None:
    """Write ``arrays`` as one uncompressed ``.npz`` at exactly ``target`` (a path: no ``.npz`` is appended; or an
    open binary file). Object arrays are refused (a checkpoint holds no pickles).

    Example:
        >>> import io
        >>> buf = io.BytesIO()
        >>> save_npz(buf, a=np.arange(3, dtype=np.int32), text=np.array("{}"))
        >>> _ = buf.seek(0)
        >>> with np.load(buf) as z: z["a"].tolist(), str(z["text"])
        ([0, 1, 2], '{}')
    """
    with zipfile.ZipFile(target, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            array = np.asarray(value, order="C")  # a view when it already is C-ordered (every checkpoint is)
            if array.dtype.hasobject:
                raise ValueError(f"save_npz: {name} is an object array (a pickle); a checkpoint holds none")
            with archive.open(f"{name}.npy", mode="w", force_zip64=True) as member:
                _write_header(member, array)
                member.write(array.reshape(-1).view(np.uint8).data)  # a memoryview of the array's own memory


def _write_header(member: IO[bytes], array: np.ndarray) -> None:
    header = np.lib.format.header_data_from_array_1_0(array)
    try:
        np.lib.format.write_array_header_1_0(member, header)
    except ValueError:  # a header over 64 KiB (very many dimensions or fields): format 2.0 allows it
        np.lib.format.write_array_header_2_0(member, header)
