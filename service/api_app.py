"""The API's FastAPI application. Run it with ``uvicorn service.api_app:create_app --factory`` or ``panogs serve``.

``create_app`` builds everything the routes use (settings, sessions, storage, key verifier, the Celery app
used to publish jobs by name, the result cache and the lazily started text-encoder process) and keeps it in
``app.state``; nothing happens at import time.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service.api.routes import (
    artifacts,
    health,
    instances,
    jobs,
    map_models,
    renders,
    scenes,
    uploads,
    viewer_scene,
    web_app,
)
from service.auth import KeyVerifier
from service.body_limit import BodyLimit
from service.bundle_check import BundleOpener
from service.cache import TTLCache
from service.db.session import get_session_factory
from service.encoder import EncoderProcess
from service.errors import install_error_handlers
from service.job_results import ResultCache
from service.json_body import BoundedJsonBody, body_limits
from service.map_models import features_folders
from service.queue import Sender, celery_sender
from service.reaper import Reaper
from service.security_headers import SecurityHeaders
from service.settings import Settings, get_settings
from service.storage import HashStates
from service.storage.backends import open_storage
from service.uploads import ActiveUploads

logger = logging.getLogger(__name__)

API_PREFIX = "/v1"
DESCRIPTION = """Open-vocabulary 3D panoptic segmentation (PanoGS) as a batch service.

Upload a scene bundle (tus 1.0 resumable uploads), make a scene of it (validated), run a job on it, poll the
job, then read its instances, download its outputs and query it by text or vector. Every request but the
health checks carries an API key (`Authorization: Bearer pgs_...`); a key sees only its own uploads, scenes
and jobs. Errors are JSON: `{"type": ..., "message": ..., "problems": [...]}`.
"""


def create_app(settings: Settings | None = None, *, sender: Sender | None = None, run_reaper: bool = True) -> FastAPI:
    """The application for ``settings`` (default: from the environment).

    Args:
        settings: Infrastructure settings.
        sender: Publishes tasks by name (default: a Celery app for ``settings.broker``).
        run_reaper: Sweep for lost and unpublished jobs in a background thread while the app runs.
    """
    settings = settings or get_settings()
    settings.ensure_dirs()
    factory = get_session_factory(settings.database)
    storage = open_storage(settings)
    sender = sender or celery_sender(settings)
    encoder = EncoderProcess(settings.text_model_path, features_folders(settings))
    reaper = Reaper(settings, factory, sender, storage) if run_reaper else None

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        if reaper is not None:
            reaper.start()
        try:
            yield
        finally:
            if reaper is not None:
                reaper.stop()
            encoder.close()

    app = FastAPI(
        title="panogs",
        version="0.1.0",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url="/docs",
        openapi_url="/openapi.json",
    )
    app.state.settings = settings
    app.state.session_factory = factory
    app.state.storage = storage
    app.state.sender = sender
    app.state.key_verifier = KeyVerifier(settings.api_key_cache_s)
    app.state.status_cache = TTLCache(settings.status_cache_s)
    app.state.hashes = HashStates()
    app.state.active_uploads = ActiveUploads()
    app.state.results = ResultCache(settings.result_cache_size)
    app.state.bundle_opener = BundleOpener(
        settings.validation_slots, settings.validation_cpu_s, settings.validation_memory_bytes
    )
    app.state.encoder = encoder
    install_error_handlers(app)
    app.include_router(health.router)
    for router in (
        uploads.router,
        scenes.router,
        jobs.router,
        map_models.router,
        instances.router,
        artifacts.router,
        viewer_scene.router,
    ):
        app.include_router(router, prefix=API_PREFIX)
    app.include_router(renders.router, prefix=API_PREFIX)  # renders of a finished job
    app.include_router(web_app.router)
    app.add_middleware(BoundedJsonBody, limits=body_limits(settings))  # inside BodyLimit: it sees capped bodies only
    app.add_middleware(BodyLimit, limit=settings.max_json_body_bytes)
    app.add_middleware(SecurityHeaders)  # added last: the outermost, so that every answer carries the headers
    return app
