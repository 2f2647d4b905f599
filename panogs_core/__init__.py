"""panogs_core: the PanoGS algorithm library (open-vocabulary 3D panoptic segmentation).

Pure functions and small frozen dataclasses, arrays in and arrays out. Importing the package is cheap and
imports neither torch nor open3d: each stage module imports what it needs. The entry points are
``panogs_core.io.bundle.reader.open_bundle``, ``panogs_core.pipeline.run.run_pipeline`` and
``panogs_core.language.query.query_instances``; docs/architecture.md places every subpackage.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
