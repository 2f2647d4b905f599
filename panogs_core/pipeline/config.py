"""The pipeline configuration: one frozen dataclass per stage, composed, with a strict YAML round trip.

Each stage module owns its ``*Config``; this module only composes them. ``from_dict`` / ``from_yaml`` reject
unknown keys (a typo is an error, not a silently ignored setting) and ``to_dict`` / ``to_yaml`` write every field,
so a job's snapshot reproduces the run.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml

from panogs_core.errors import ConfigError
from panogs_core.gaussians.config import AppearanceConfig
from panogs_core.stages.affinity import AffinityConfig
from panogs_core.stages.clustering import ClusteringConfig
from panogs_core.stages.fusion import FusionConfig
from panogs_core.stages.labeling import LabelingConfig
from panogs_core.stages.language_field.config import LanguageFieldConfig
from panogs_core.stages.maps2d.config import Maps2DConfig
from panogs_core.stages.primitives import PrimitivesConfig
from panogs_core.stages.superprimitives import SuperPrimitiveConfig
from panogs_core.stages.visibility import VisibilityConfig

T = TypeVar("T")


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    """Every setting of a pipeline run. Defaults follow the reference's ScanNet settings."""

    # The 2D-maps stage: only a bundle without masks or feature maps runs it (with the models the caller names).
    maps2d: Maps2DConfig = field(default_factory=Maps2DConfig)
    primitives: PrimitivesConfig = field(default_factory=PrimitivesConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    language_field: LanguageFieldConfig = field(default_factory=LanguageFieldConfig)
    superprimitives: SuperPrimitiveConfig = field(default_factory=SuperPrimitiveConfig)
    affinity: AffinityConfig = field(default_factory=AffinityConfig)
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    labeling: LabelingConfig = field(default_factory=LabelingConfig)
    # Which per-primitive language features feed the graph cut and the labels: the distilled tri-plane field
    # (the method) or the fused multi-view means directly (the paper's "w/o field" ablation).
    features_source: Literal["field", "fused"] = "field"

    def to_dict(self) -> dict[str, Any]:
        """Every field, nested, with tuples as lists (YAML/JSON friendly)."""
        return _to_plain(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> PipelineConfig:
        """Build from a (partial) nested dict; missing keys keep their defaults, unknown keys are refused."""
        return _from_plain(cls, data or {}, path="config")

    def to_yaml(self) -> str:
        """YAML text of :meth:`to_dict`."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def from_yaml(cls, text_or_path: str | Path) -> PipelineConfig:
        """Parse YAML text, or read it from a path."""
        text = str(text_or_path)
        if isinstance(text_or_path, Path) or (len(text) < 4096 and "\n" not in text and Path(text).is_file()):
            text = Path(text_or_path).read_text()
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"config: not valid YAML: {exc}") from exc
        except RecursionError:  # the YAML parser recurses per level of nesting; no config is nested that deep
            raise ConfigError("config: nested too deeply to be a pipeline config") from None
        if data is not None and not isinstance(data, dict):
            raise ConfigError(f"config: expected a mapping at the top level, found {type(data).__name__}")
        return cls.from_dict(data)

    def with_overrides(self, overrides: dict[str, Any] | None) -> PipelineConfig:
        """A copy with a nested dict of overrides applied (same rules as :meth:`from_dict`)."""
        merged = _deep_merge(self.to_dict(), overrides or {})
        return PipelineConfig.from_dict(merged)


def _to_plain(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [_to_plain(v) for v in obj]
    return obj


def _deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _from_plain(cls: type[T], data: Any, *, path: str) -> T:
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping, found {data!r}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {unknown}; known keys are {sorted(known)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, path=f"{path}.{name}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{path}: {exc}") from exc


def _coerce(hint: Any, value: Any, *, path: str) -> Any:
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return _from_plain(hint, value, path=path)
    origin = typing.get_origin(hint)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{path}: expected a list, found {value!r}")
        args = typing.get_args(hint)
        item = args[0] if args else Any
        return tuple(_coerce(item, v, path=f"{path}[{i}]") for i, v in enumerate(value))
    if origin is typing.Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ConfigError(f"{path}: expected one of {list(allowed)}, found {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(arg, value, path=path)
            except ConfigError:
                continue
        raise ConfigError(f"{path}: {value!r} does not match {hint}")
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{path}: expected a number, found {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, found {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, found {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, found {value!r}")
        return value
    return value
