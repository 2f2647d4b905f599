"""File formats and dataset layouts: the readers and writers that several parts of the core share.

``bundle/`` is the scene-bundle format (reader, validation, writer, archives), ``importers/`` turn dataset layouts
(ScanNet, Replica) into bundles, ``run_folder`` reads a finished run's folder back (``stages/export.py`` writes it),
``ground_truth`` reads evaluation labels, and ``ply``, ``image_header``, ``npy_header`` and ``run_json`` read
(``ply`` also writes) one file type each, with errors that name the file; ``npz`` writes the checkpoints' ``.npz``
files without copying their arrays. The bounded JSON reader is ``panogs_core.bounded_json``, a floor below, since
the language package reads with it too (``io/bounded_json.py`` only re-exports it for the service's imports).
Files that belong to one module stay with it: each stage output's checkpoint (``save`` / ``load``), the exports,
the appearance fit's snapshots, the renders and the synthetic scenes.
"""
