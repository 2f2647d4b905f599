"""Celery worker: runs a job's pipeline stages through panogs_core and records progress in the database."""
