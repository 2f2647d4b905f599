"""The text encoder for free-text queries, kept in a child process so that the API process never imports
torch.

The child is spawned (not forked) on the first free-text query and keeps its encoders loaded, so every query
after the first is warm. Requests are serialised over a pipe; an encoder error in the child comes back as the
same exception type where it is known (``EncoderUnavailableError``), otherwise as ``EncoderFailed``.
A class-name or vector query never reaches the child.

A scene whose features the 2D-maps stage computed (space ``clip-vit-...@<hash>``) is embedded by the text tower of
the operator's features entry whose folder holds those weights (``service.map_models.text_model_for``), never by
another model.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
from collections import OrderedDict
from multiprocessing.connection import Connection
from typing import Any

logger = logging.getLogger(__name__)

CALL_TIMEOUT_S = 120.0  # the first call loads the model


class EncoderFailed(RuntimeError):
    """The encoder process failed or died."""


def _serve(conn: Connection, model_path: str | None, folders: dict[str, str]) -> None:  # pragma: no cover - child
    # One sentence is a tiny forward pass: one thread answers it fastest, and several threads spin against the
    # API and the workers on a busy machine (measured: 30 ms with one thread, 250-500 ms with two).
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import numpy as np

    from panogs_core.language.text_encoders import get_text_encoder
    from service.map_models import text_model_for

    spaces: dict[str, str] = {}  # features entry -> its folder's space, read once
    while True:
        try:
            request = conn.recv()
        except EOFError:
            return
        if request is None:
            return
        space, texts = request
        try:
            path = text_model_for(space, model_path, folders, spaces)
            encoder = get_text_encoder(space, model_path=path)
            vectors = np.asarray(encoder.encode(list(texts)), dtype=np.float32)
            conn.send(("ok", vectors))
        except Exception as exc:  # every failure goes back to the API process, typed by name
            conn.send(("error", (type(exc).__name__, str(exc))))


class EncoderProcess:
    """A lazily spawned child that encodes texts; thread-safe, one request at a time.

    Embeddings of single texts are remembered (LRU, ``CACHE_SIZE``): a repeated query skips the encoder.
    """

    CACHE_SIZE = 1024

    def __init__(self, model_path: str | None = None, features_folders: dict[str, str] | None = None) -> None:
        self._model_path = model_path
        self._folders = dict(features_folders or {})  # PANOGS_MAP_MODELS' features entries: name -> folder
        self._lock = threading.Lock()
        self._conn: Connection | None = None
        self._proc: Any = None
        self._cache: OrderedDict[tuple[str, str], Any] = OrderedDict()

    def _ensure(self) -> Connection:
        if self._conn is not None and self._proc is not None and self._proc.is_alive():
            return self._conn
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve, args=(child, self._model_path, self._folders), name="panogs-text-encoder", daemon=True
        )
        self._proc.start()
        child.close()
        self._conn = parent
        logger.info("text encoder process started (pid %s)", self._proc.pid)
        return parent

    def encode(self, space: str, texts: list[str]) -> Any:
        """(n, D) float32 unit rows for ``texts`` in ``space``."""
        key = (space, texts[0]) if len(texts) == 1 else None
        with self._lock:
            if key is not None and key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
            result = self._call(space, texts)
            if key is not None:
                self._cache[key] = result
                while len(self._cache) > self.CACHE_SIZE:
                    self._cache.popitem(last=False)
            return result

    def _call(self, space: str, texts: list[str]) -> Any:
        """One round trip to the child; the caller holds ``self._lock``."""
        conn = self._ensure()
        try:
            conn.send((space, texts))
            if not conn.poll(CALL_TIMEOUT_S):
                self._kill()
                raise EncoderFailed(f"the text encoder did not answer within {CALL_TIMEOUT_S:g} s")
            status, payload = conn.recv()
        except (EOFError, OSError, BrokenPipeError) as exc:
            self._kill()
            raise EncoderFailed(f"the text encoder process died: {exc!r}") from exc
        if status == "ok":
            return payload
        name, message = payload
        if name == "EncoderUnavailableError":
            from panogs_core.errors import EncoderUnavailableError

            raise EncoderUnavailableError(message)
        raise EncoderFailed(f"{name}: {message}")

    def _kill(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=5)
        self._conn = None
        self._proc = None

    def close(self) -> None:
        """Stop the child, if it runs."""
        with self._lock:
            if self._conn is not None:
                try:
                    self._conn.send(None)
                except OSError:
                    pass
            if self._proc is not None:
                self._proc.join(timeout=5)
            self._kill()


class RemoteTextEncoder:
    """A ``panogs_core.language.text_encoders.TextEncoder`` whose work happens in the encoder process."""

    def __init__(self, process: EncoderProcess, space: str, dim: int) -> None:
        self._process = process
        self.space = space
        self.dim = dim

    def encode(self, texts: list[str]) -> Any:
        """(n, D) float32 unit rows."""
        return self._process.encode(self.space, texts)
