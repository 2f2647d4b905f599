"""PLY files: write binary little-endian vertices (+ optional triangles), read the vertices of any PLY.

The reader understands the three encodings of the format (``ascii``, ``binary_little_endian``,
``binary_big_endian``), skips elements it is not asked for (faces with list properties included) and raises
:class:`InputError` naming the file for anything malformed. Only the ``vertex`` element is ever decoded: its
properties come back as 1-D arrays in file order, with the dtype of the file (native byte order).

What a file may cost is bounded by a :class:`PlyBudget` before the work is done: the vertices, the values of an
ASCII body parsed up to the vertices, and the rows parsed one at a time in Python (an element with list
properties: faces written before the vertices, or lists on the vertices themselves). Data is read in chunks, so
:func:`scan_ply_positions` (validation) holds one chunk at a time, whatever the file's size.
"""

from panogs_core.io.ply.read import PlyBudget, read_ply_vertices, scan_ply_positions, vertex_count
from panogs_core.io.ply.write import write_ply

__all__ = ["PlyBudget", "read_ply_vertices", "scan_ply_positions", "vertex_count", "write_ply"]
