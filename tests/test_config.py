"""Config machinery: YAML round trip, partial files, unknown keys, wrong types, range checks."""

from dataclasses import dataclass, field
from typing import Literal, Optional

import pytest

from comreg_core.config import ConfigError, from_dict, load_config, require, to_dict, write_config


@dataclass(frozen=True)
class Inner:
    width_mm: float = 51.0
    shape: tuple[int, int] = (4, 5)


@dataclass(frozen=True)
class Outer:
    count: int = 3
    mode: Literal["sweep", "uniform"] = "sweep"
    seed: Optional[int] = None
    inner: Inner = field(default_factory=Inner)

    def __post_init__(self):
        require(self.count > 0, "count", "must be positive")


def test_yaml_round_trip_and_partial_override(tmp_path):
    config = from_dict(Outer, {"count": 7, "inner": {"width_mm": 40}})
    assert config == Outer(count=7, inner=Inner(width_mm=40.0))
    path = write_config(config, tmp_path / "c.yaml")
    assert load_config(Outer, path) == config
    assert load_config(Outer, path, {"inner": {"shape": [1, 2]}}).inner == Inner(40.0, (1, 2))
    assert to_dict(Outer())["inner"]["shape"] == [4, 5]


@pytest.mark.parametrize("data, message", [
    ({"cout": 1}, "Unknown config key"),
    ({"count": "three"}, "must be an integer"),
    ({"count": 0}, "must be positive"),
    ({"mode": "spiral"}, "not one of"),
    ({"inner": {"width_mm": "wide"}}, "inner.width_mm"),
    ({"inner": {"shape": [1]}}, "needs 2 items"),
])
def test_bad_values_raise_config_error(data, message):
    with pytest.raises(ConfigError, match=message):
        from_dict(Outer, data)


def test_bad_yaml_file(tmp_path):
    (tmp_path / "bad.yaml").write_text("count: [1,\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(Outer, tmp_path / "bad.yaml")
