"""PipelineConfig: composition, strict YAML round trip, overrides."""

from __future__ import annotations

import pytest

from panogs_core.errors import ConfigError
from panogs_core.pipeline.config import PipelineConfig


def test_defaults_round_trip_through_yaml() -> None:
    cfg = PipelineConfig()
    again = PipelineConfig.from_yaml(cfg.to_yaml())
    assert again == cfg


def test_reference_defaults() -> None:
    cfg = PipelineConfig()
    assert cfg.visibility.depth_rtol == pytest.approx(0.07)
    assert tuple(cfg.clustering.thresholds) == (0.9, 0.8, 0.7, 0.6)
    assert cfg.superprimitives.min_size == 20


def test_partial_override_keeps_other_defaults() -> None:
    cfg = PipelineConfig.from_dict({"clustering": {"thresholds": [0.9, 0.7]}})
    assert cfg.clustering.thresholds == (0.9, 0.7)
    assert cfg.visibility == PipelineConfig().visibility


def test_with_overrides_nested() -> None:
    cfg = PipelineConfig().with_overrides({"visibility": {"depth_rtol": 0.05}, "features_source": "fused"})
    assert cfg.visibility.depth_rtol == pytest.approx(0.05)
    assert cfg.features_source == "fused"


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"clustring": {}}, r"unknown key\(s\) \['clustring'\]"),
        ({"visibility": {"depth_rtl": 0.1}}, r"config\.visibility: unknown key"),
        ({"visibility": {"depth_rtol": "high"}}, r"config\.visibility\.depth_rtol: expected a number"),
        ({"features_source": "pixels"}, r"features_source: expected one of"),
        ({"clustering": {"thresholds": 0.9}}, r"thresholds: expected a list"),
    ],
)
def test_bad_config_names_the_field(data: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        PipelineConfig.from_dict(data)


def test_invalid_value_rejected_by_stage_validation() -> None:
    with pytest.raises(ConfigError, match="depth_rtol"):
        PipelineConfig.from_dict({"visibility": {"depth_rtol": -1.0}})


def test_yaml_must_be_a_mapping() -> None:
    with pytest.raises(ConfigError, match="mapping"):
        PipelineConfig.from_yaml("- 1\n- 2\n")
