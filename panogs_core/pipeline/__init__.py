"""The pipeline: ``run.run_pipeline`` runs the stages of ``stage_table.PIPELINE`` in order (each entry says how
its stage is called, what it reads and writes, and how its checkpoint key is made), ``checkpoints`` keeps their
outputs under ``stages/``, ``report`` writes ``report.json``, ``result`` is what a run hands back, ``config``
composes the stages' settings and ``profiling`` measures each stage's time and memory for the report."""
