"""The Alembic migrations, shipped inside the package (``service.db.migrate`` finds them with importlib.resources).

``env.py`` and ``versions/`` are Alembic scripts: Alembic runs them, nothing imports them.
"""
