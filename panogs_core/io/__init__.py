"""File formats and dataset layouts: the only part of the core that touches paths (besides ``bundle.py``).

``ply`` reads and writes PLY vertices, ``writer`` writes scene bundles, ``archive`` extracts uploaded bundle
archives safely, ``scannet`` / ``replica`` convert those dataset layouts into bundles, and ``ground_truth`` reads
evaluation labels (``.npz`` or ScanNet's annotation files).
"""

from __future__ import annotations

from panogs_core.io.ply import read_ply_vertices, write_ply
from panogs_core.io.writer import BundleWriter, ImportReport

__all__ = ["BundleWriter", "ImportReport", "read_ply_vertices", "write_ply"]
