"""Building-scale scenes as tiles: the plan (``plan.py``), a tile as a bundle (``view.py``), the merge
(``merge.py``) and the tiled run (``runner.py``); docs/method.md §16."""
