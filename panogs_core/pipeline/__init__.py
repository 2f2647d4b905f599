"""The pipeline: ``run.run_pipeline`` runs the stages in order, ``stage_table`` says what each stage reads and how
its checkpoint key is made, ``config`` composes the stages' settings, ``snapshots`` keeps a long stage's partial work
and ``profiling`` measures each stage's time and memory for the report."""
