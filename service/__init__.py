"""The panogs batch service: FastAPI app, database models and settings. Never imports torch."""
