"""The operator's 2D models as jobs name them: entry names checked against ``PANOGS_MAP_MODELS``, never paths.

A job names an entry per kind of map (``masks``, ``features``); the API refuses a name the settings do not hold
(with the known ones of that kind) and a job that leaves a kind of map its scene's bundle lacks without a model.
The worker turns the names into the folders of its own settings (:func:`entry_folders`); the API's text encoder
finds the features entry whose folder computed a scene's ``clip-...@<hash>`` space (:func:`features_folders`).
No torch here: the identities are read from the folders' files (``panogs_core.language.model_identity``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from service.errors import InvalidInput
from service.schemas import InlineVocabulary, JobCreate
from service.settings import Settings

KINDS = ("masks", "features")


def _known(settings: Settings, kind: str) -> str:
    names = settings.map_model_names(kind)
    return ", ".join(repr(n) for n in names) if names else "none (the operator declares them in PANOGS_MAP_MODELS)"


def check_job_maps(settings: Settings, body: JobCreate, scene: Any) -> dict[str, Any]:
    """The job row's ``maps`` column for a request: the entry names per kind, or None for a kind it leaves.

    Raises:
        InvalidInput: a name that is no entry of that kind (listing the known ones), a kind of map the scene's
            bundle lacks with no entry named for it, an entry named for a kind the bundle brings (the run keeps
            the bundle's), forced tiles on a job that computes maps, or inline embeddings whose width is not
            the named features model's.
    """
    maps, tiling = body.maps, body.tiling
    asked = {kind: getattr(maps, kind) if maps is not None else None for kind in KINDS}
    problems = []
    for kind, name in asked.items():
        if name is None:
            continue
        entry = settings.map_models.get(name)
        if entry is None or entry.kind != kind:
            problems.append(f"maps.{kind}: {name!r} is no {kind} model of this server; known: {_known(settings, kind)}")
    has = {"masks": bool(scene.has_mask_maps), "features": bool(scene.has_feature_maps)}
    for kind in KINDS:
        if not has[kind] and asked[kind] is None:
            problems.append(
                f"maps.{kind}: scene {scene.id}'s bundle has no {_map_word(kind)}; name a {kind} model to compute "
                f"them (known: {_known(settings, kind)}) or upload a bundle with them"
            )
        elif has[kind] and asked[kind] is not None:
            # The pipeline never recomputes a kind the bundle brings: a model named for it would do nothing.
            problems.append(
                f"maps.{kind}: scene {scene.id}'s bundle brings its own {_map_word(kind)}, which the run uses; "
                f"leave maps.{kind} out"
            )
    if problems:
        raise InvalidInput("the 2D models of the job are not valid", problems=problems)
    if any(asked.values()) and tiling is not None and tiling.tiles not in ("auto", "off"):
        # The maps of a frame serve every tile that sees it: they are computed once, for the whole scene.
        raise InvalidInput(f"tiling.tiles {tiling.tiles!r}: a job that computes 2D maps runs its scene whole")
    if asked["features"] is not None and isinstance(body.vocabulary, InlineVocabulary):
        _check_embedding_width(settings, asked["features"], body.vocabulary.embedding_dim)
    return asked


def _check_embedding_width(settings: Settings, name: str, width: int | None) -> None:
    """Refuse inline embeddings whose width is not the features model's (its config's ``projection_dim``); a
    folder the API cannot read is left to the worker, which reads it before any frame."""
    from panogs_core.language.model_identity import ModelLoadError, read_config

    if width is None:
        return
    try:
        dim = read_config(Path(settings.map_models[name].path)).get("projection_dim")
    except ModelLoadError:
        return
    if isinstance(dim, int) and dim != width:
        raise InvalidInput(
            f"vocabulary.classes[*].embedding: {width} values per class, but the features model {name!r} "
            f"writes {dim}-d features; give {dim}-d embeddings or leave them out to have the names embedded"
        )


def _map_word(kind: str) -> str:
    return "instance mask maps" if kind == "masks" else "language feature maps"


def computes_maps(maps: dict[str, Any] | None) -> bool:
    """Whether a job's ``maps`` column names any model (the job runs the 2D-maps stage)."""
    return maps is not None and any(maps.get(kind) for kind in KINDS)


def job_queue(settings: Settings, maps: dict[str, Any] | None) -> str:
    """The Celery queue of a new job: ``maps_queue`` when it computes 2D maps and one is set, else ``job_queue``."""
    if computes_maps(maps) and settings.maps_queue:
        return settings.maps_queue
    return settings.job_queue


def entry_folders(settings: Settings, maps: dict[str, Any] | None) -> dict[str, str | None]:
    """The folders (``masks``, ``features``) of the entries a job named, from this process's settings.

    Raises:
        InvalidInput: an entry the job named is not in these settings (the API's and the worker's differ).
    """
    folders: dict[str, str | None] = dict.fromkeys(KINDS)
    for kind in KINDS:
        name = (maps or {}).get(kind)
        if name is None:
            continue
        entry = settings.map_models.get(name)
        if entry is None or entry.kind != kind:
            raise InvalidInput(
                f"map model entry {name!r} ({kind}): not in this worker's PANOGS_MAP_MODELS (known: "
                f"{_known(settings, kind)}); set the same entries on the API and the workers"
            )
        folders[kind] = entry.path
    return folders


def features_folders(settings: Settings) -> dict[str, str]:
    """Entry name -> folder of every features entry: where the text tower of a ``clip-...@<hash>`` space is."""
    return {name: e.path for name, e in sorted(settings.map_models.items()) if e.kind == "features"}


def text_model_for(space: str, model_path: str | None, folders: dict[str, str], spaces: dict[str, str]) -> str | None:
    """The folder whose text tower embeds free text in ``space``.

    For a ``clip-vit-...@<hash>`` space (features computed by the 2D-maps stage): the features entry whose folder
    has that identity, else ``model_path`` (which the encoder loads only if it holds the same weights), else an
    error naming the entries and their spaces: never another model. Any other space: ``model_path``.

    Args:
        space: The scene's ``features.space``.
        model_path: ``PANOGS_TEXT_MODEL_PATH``.
        folders: :func:`features_folders`.
        spaces: Entry name -> its folder's space, filled here (hashing a folder's weights takes seconds: once).

    Raises:
        EncoderUnavailableError: a model space that no entry and not ``model_path`` can embed.
    """
    from panogs_core.errors import EncoderUnavailableError
    from panogs_core.language.model_identity import ModelLoadError, clip_space, resolve_model_dir, split_space

    arch, digest = split_space(space)
    if digest is None or not arch.startswith("clip-vit-"):
        return model_path
    for name, folder in folders.items():
        if name not in spaces:
            try:
                spaces[name] = clip_space(resolve_model_dir(folder))
            except ModelLoadError as exc:
                spaces[name] = f"unreadable ({exc})"
        if spaces[name] == space:
            return folder
    if model_path is not None:
        return model_path
    seen = "; ".join(f"{name}: {spaces[name]}" for name in folders) or "none declared"
    raise EncoderUnavailableError(
        f"{space}: no features entry of PANOGS_MAP_MODELS holds the CLIP weights that computed this scene's "
        f"features (entries: {seen}); add that model's folder as an entry, or query with vocabulary class names "
        "or a vector"
    )
