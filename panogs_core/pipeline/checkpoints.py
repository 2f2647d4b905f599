"""The checkpoint store of a run: each stage's output under ``out_dir/stages/`` with the key it was made with.

A stage's key is a hash of the bundle's hash, the keys of the stages it reads and exactly the settings it reads
(:func:`panogs_core.pipeline.stage_table.stage_keys`), so a crashed job resumes from its last finished stage and a
re-run with new clustering thresholds reuses the fusion and the distilled field. ``stages/manifest.json`` records
the key of every checkpoint in place; a stage whose recorded key matches is read back instead of computed.

Checkpoints are written by one thread beside the next stages; a key is recorded only once its file is in place, a
failed write ends the run with its error, and the bundle's hash (SHA-256 over every file) is computed in a thread
beside the stages (:class:`StageKeys`). A :class:`SharedCheckpoints` store (the service's, per scene)
is asked for a checkpoint this folder lacks and given each one this run computes.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol

from panogs_core.io.bundle import Bundle
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.input_hash import hash_bundle
from panogs_core.pipeline.lane import background_turn
from panogs_core.pipeline.profiling import StageStats
from panogs_core.pipeline.stage_table import Checkpoint, StageSpec, stage_keys
from panogs_core.snapshots import StageSnapshot
from panogs_core.stages.maps2d.stage import maps_key
from panogs_core.types import Vocabulary

log = logging.getLogger(__name__)


class SharedCheckpoints(Protocol):
    """Checkpoints kept beyond one run folder (the service keeps them under the scene, by key): a run whose stage
    key was computed before fetches the checkpoint instead of computing the stage, and stores what it computed."""

    def fetch(self, stage: str, key: str, dest: Path) -> bool:
        """Write the checkpoint of ``stage`` under ``key`` to ``dest`` (whole) and return True; False when there
        is none, and then this run computes it (and calls :meth:`store`)."""
        ...

    def store(self, stage: str, key: str, path: Path) -> None:
        """Keep the checkpoint at ``path``, just computed, for later runs."""
        ...

    def known_input_hash(self) -> str | None:
        """A hash that names this bundle's bytes, known without reading them, or None (then the run hashes the
        bundle, :func:`hash_bundle`): as an earlier run of the same bundle kept it (a scene's bundle never changes,
        and hashing it is most of a re-run's time at ScanNet size), or made from the SHA-256 of the archive it was
        uploaded as (the service's ``worker/shared_checkpoints.py``)."""
        ...

    def keep_input_hash(self, sha256: str) -> None:
        """Keep the bundle's hash, computed by this run, for the later runs of the same bundle."""
        ...


class Manifest:
    """Stage outputs under ``stages/`` with a manifest of the key each was made with."""

    def __init__(self, root: Path, enabled: bool) -> None:
        self.root = root
        self.enabled = enabled
        root.mkdir(parents=True, exist_ok=True)
        self._manifest_path = root / "manifest.json"
        self.manifest: dict[str, str] = {}
        if enabled and self._manifest_path.is_file():
            self.manifest = json.loads(self._manifest_path.read_text())

    def path(self, stage: str) -> Path:
        return self.root / f"{stage}.npz"

    def snapshot(self, stage: str, key: str) -> StageSnapshot:
        """Where ``stage`` keeps its partial work under ``key``; read only when resuming."""
        return StageSnapshot(self.root / f"{stage}.partial.pt", key, readable=self.enabled)

    def may_have(self, stage: str) -> bool:
        """Whether a checkpoint of ``stage`` might be reused (its key is then needed before the stage runs)."""
        return self.enabled and stage in self.manifest and self.path(stage).is_file()

    def record(self, stage: str, key: str) -> None:
        self.manifest[stage] = key
        self._write_manifest()

    def forget(self, stage: str) -> None:
        """Drop the key of ``stage`` (its file is about to change and its new key is not known yet)."""
        if self.manifest.pop(stage, None) is not None:
            self._write_manifest()

    def _write_manifest(self) -> None:
        tmp = self._manifest_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.manifest, indent=1))
        tmp.replace(self._manifest_path)


# Niceness added to the hashing thread: the stages' own threads come first, the hash takes the cores they leave.
_HASH_NICENESS = 10


def _hash_at_low_priority(scene: Bundle) -> str:
    """:func:`hash_bundle`, on Linux at a niceness ``_HASH_NICENESS`` above the process's (per thread there).

    The stages run their frames on threads (``--threads``); at the same priority the hash took a third of the two
    cores while fusion read its frames, and the run waits for it only at its end, when the cores are idle.
    """
    if sys.platform.startswith("linux"):  # a thread's id names that thread only on Linux
        tid = threading.get_native_id()
        try:
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + _HASH_NICENESS))
        except OSError:  # not allowed here: hash at the process's priority
            pass
    return hash_bundle(scene)


class StageKeys(Mapping[str, str]):
    """The stages' checkpoint keys, made from the bundle's hash once it is ready.

    Hashing the bundle reads every file of it (2 GB at ScanNet size, about 1.5 CPU s): it runs in a thread (hashlib
    and file reads release the GIL) while stages compute, and a stage waits for it only to look up or to record its
    checkpoint. The thread runs at a lower priority (:func:`_hash_at_low_priority`). With ``start=False`` it starts
    on :meth:`start`, or when a key is first asked for: a run with no checkpoint to look up starts it once the
    stages that keep every core busy are done (``pipeline.run``).
    """

    def __init__(
        self,
        scene: Bundle,
        cfg: PipelineConfig,
        vocab: Vocabulary,
        known_hash: str | None = None,
        *,
        start: bool = True,
    ) -> None:
        self._scene = scene
        self._hash: Future[str] = Future()
        self._start_lock = threading.Lock()
        self._started = known_hash is not None
        if known_hash is not None:
            self._hash.set_result(known_hash)
        elif start:
            self.start()
        self._cfg, self._vocab = cfg, vocab
        self._maps = maps_key(scene)
        self._keys: dict[str, str] | None = None

    def start(self) -> None:
        """Start hashing the bundle in a thread, once (later calls do nothing)."""
        with self._start_lock:
            if self._started:
                return
            self._started = True
        # A daemon thread: a run that fails before it needs the hash does not wait for it to exit.
        threading.Thread(target=self._compute_hash, name="hash-bundle", daemon=True).start()

    def _compute_hash(self) -> None:
        try:
            self._hash.set_result(_hash_at_low_priority(self._scene))
        except BaseException as exc:  # raised where the hash is read
            self._hash.set_exception(exc)

    def ready(self) -> bool:
        """Whether the bundle's hash is done (the keys are then known without waiting)."""
        return self._hash.done()

    @property
    def input_hash(self) -> str:
        """The bundle's SHA-256 (starts the hashing if it has not started; waits for it; raises what it raised)."""
        self.start()
        return self._hash.result()

    def _resolved(self) -> dict[str, str]:
        if self._keys is None:
            self._keys = stage_keys(self.input_hash, self._cfg, self._vocab, self._maps)
        return self._keys

    def __getitem__(self, name: str) -> str:
        return self._resolved()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._resolved())

    def __len__(self) -> int:
        return len(self._resolved())


class CheckpointStore:
    """Loads a stage's checkpoint when its key matches, else computes the stage and writes its checkpoint in a
    writer thread; records each key once its file is in place (and once the key is known)."""

    def __init__(self, stages_dir: Path, resume: bool, shared: SharedCheckpoints | None) -> None:
        self.manifest = Manifest(stages_dir, resume)
        self.shared = shared if resume else None
        self._unrecorded: list[str] = []  # stages whose checkpoint is written, waiting for their key
        # Checkpoints are written by one thread beside the next stages (the field's and the fusion's are 0.2-0.4 s
        # of file writes each at ScanNet size, and with a shared store an upload); the manifest is the two
        # threads' only shared state, under this lock.
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="checkpoint-writer")
        self._writes: list[Future[None]] = []
        self._book = threading.Lock()

    def snapshot(self, stage: str, key: str) -> StageSnapshot:
        """Where ``stage`` keeps its partial work under ``key`` (see :mod:`panogs_core.snapshots`)."""
        return self.manifest.snapshot(stage, key)

    def may_reuse(self) -> bool:
        """Whether a stage might be read back rather than computed (a resumed run folder with a manifest, or a
        shared store): its key, so the bundle's hash, is then needed as soon as the stages start."""
        return self.shared is not None or (self.manifest.enabled and bool(self.manifest.manifest))

    def load_or_compute(self, spec: StageSpec, keys: StageKeys, compute: Callable[[], Any], stats: StageStats) -> Any:
        """Load the checkpoint of ``spec`` if its key matches (``stats.cached``), else compute and save it.

        The key is waited for only when a checkpoint of the stage exists (the keys hash the whole bundle, which
        the first stages need not wait for: :class:`StageKeys`); else the checkpoint is recorded once it is known.
        """
        self.record_checkpoints(keys, wait=False)  # what the stages before have written, if it can be
        path = self.manifest.path(spec.name)
        if spec.load is not None and self._reusable(spec.name, keys, path):
            stats.cached = True
            return spec.load(path)
        result = compute()
        self._writes.append(self._writer.submit(self._write_checkpoint, spec.name, result, path, keys))
        return result

    def record_checkpoints(self, keys: StageKeys, *, wait: bool) -> None:
        """Record the keys of the checkpoints written before the keys were known (all of them, every pending
        write finished first, when ``wait``)."""
        if wait:
            self.flush()
        else:
            self._raise_failed_write()
        with self._book:
            if self._unrecorded and (wait or keys.ready()):
                for name in self._unrecorded:
                    self._recorded(name, keys[name])
                self._unrecorded.clear()

    def flush(self) -> None:
        """Wait for every checkpoint write; raise the first one's error."""
        writes, self._writes = self._writes, []
        for write in writes:
            write.result()

    def close(self, *, failing: bool = False) -> None:
        """Finish the pending writes (a finished stage's checkpoint stays good for a resumed run) and stop the
        writer; a write's error is raised, unless the run is already failing (then it is logged)."""
        try:
            self.flush()
        except Exception:
            if not failing:
                raise
            log.exception("a checkpoint could not be written (the run failed too)")
        finally:
            self._writer.shutdown(wait=True)

    def _raise_failed_write(self) -> None:
        for write in self._writes:
            if write.done() and write.exception() is not None:
                self.flush()  # raises it

    def _recorded(self, name: str, key: str) -> str:
        """Record the checkpoint just written of ``name`` under ``key`` (its partial work is done with); ``key``."""
        self.manifest.record(name, key)
        self.manifest.snapshot(name, key).discard()
        return key

    def _write_checkpoint(self, name: str, result: Checkpoint, path: Path, keys: StageKeys) -> None:
        """Save ``result`` as the checkpoint of ``name`` (in the writer thread: no stage changes a stage's output
        in place, so it is the output as computed) and record or store it under its key."""
        tmp = path.with_suffix(".tmp.npz")
        with background_turn():  # the file's write only: the key below may wait for the hash, which takes turns too
            result.save(tmp)
        shared = self.shared
        key = None if shared is None else keys[name]  # the shared store files it under its key: wait for it
        with self._book:
            self.manifest.forget(name)  # a stale key must never name the new file
            tmp.replace(path)
            if shared is None or key is None:
                self._unrecorded.append(name)
                return
            self._recorded(name, key)
        shared.store(name, key, path)

    def _reusable(self, name: str, keys: StageKeys, path: Path) -> bool:
        """Whether ``path`` holds the stage's checkpoint for its current key: in the run folder, else fetched from
        the shared store (which needs the key, so a run with a shared store waits for the bundle's hash here)."""
        with self._book:  # the keys are read outside it: they may wait for the bundle's hash
            recorded = self.manifest.manifest[name] if self.manifest.may_have(name) else None
        if recorded is not None and recorded == keys[name]:  # no wait without a checkpoint to compare
            return True
        if self.shared is None:
            return False
        key = keys[name]
        with self._book:
            self.manifest.forget(name)  # the fetch may replace the file: no stale key may name it
        if self.shared.fetch(name, key, path):
            with self._book:
                self.manifest.record(name, key)
            return True
        return False
