"""Database layer shared by the API and the worker: models, sessions and queries."""
