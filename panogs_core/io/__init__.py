"""Files in and out: the only part of the core that reads or writes paths.

``bundle/`` is the scene-bundle format (reader, validation, writer, archives), ``importers/`` turn dataset layouts
(ScanNet, Replica) into bundles, ``run_folder`` owns the files of a finished run, ``ground_truth`` reads evaluation
labels, and ``ply``, ``bounded_json``, ``image_header``, ``npy_header``, ``run_json`` are the bounded readers and
writers of single file types that the others share.
"""
