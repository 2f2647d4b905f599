"""Celery worker: runs a job's pipeline stages through panogs_core and records progress in the database.

The worker depends on the service (settings, database, storage, broker configuration); the service never imports
the worker. Importing any module here builds no app, reads no settings and writes no file.
"""
