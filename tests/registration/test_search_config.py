"""The pose search's settings: their checks, the older names and removed switches that earlier
registration folders recorded."""

from __future__ import annotations

import pytest

from comreg_core.config import ConfigError
from comreg_core.registration.search.config import SearchConfig, as_search_config

@pytest.mark.parametrize("key, value", [
    ("shaft_rotations", 0), ("shaft_rotations", 37), ("icp_points", 2), ("target_points", 10),
    ("icp_iterations", -1),
    ("icp_trim", 1.0), ("score_trim", -0.1), ("distinct_deg", 0.0), ("distinct_mm", -1.0),
    ("min_confidence", 1.0), ("icp_schedule", ((3, 10),)), ("icp_schedule", ((128, -1),)),
    ("icp_margin_mm", 0.0), ("slide_step_mm", -1.0), ("slide_range_mm", -5.0),
    ("screen_points", 2), ("screen_iterations", -1), ("screen_score_points", 0),
    ("refine_top", -1),
    ("polish_max_distance_mm", 0.0), ("polish_iterations", 0), ("polish_top", 0),
    ("score_floor_mm", 0.0), ("patch_max_share", 0.0), ("patch_max_share", 1.5),
    ("patch_min_confidence", 1.0),
    ("facing_penalty_mm", -1.0),
])
def test_config_validation(key, value):
    with pytest.raises(ConfigError, match=f"search.{key}"):
        SearchConfig(**{key: value})


def test_config_from_settings():
    assert as_search_config(None) == SearchConfig()
    assert as_search_config(True).enabled and not as_search_config(False).enabled
    assert as_search_config({"shaft_rotations": 6}).shaft_rotations == 6
    with pytest.raises(ConfigError, match="Unknown config key"):
        as_search_config({"flips": True})
    with pytest.raises(ConfigError, match="must be an integer"):
        as_search_config({"shaft_rotations": "six"})
    with pytest.raises(ConfigError, match="search setting"):
        as_search_config(3)


#: The removed switches as every registration folder's config.yaml recorded them (defaults),
#: and ``include_coarse: false`` as ``register --ct`` (no network) recorded it.
OLD_KEYS = {"axis_flips": True, "include_coarse": True, "principal_axes_solve": True,
            "retry_ambiguous": True, "polish": True, "patch_axes": 1, "patch_orientations": 60}


def test_old_registration_configs_load_when_they_hold_what_survived(tmp_path):
    import yaml

    from comreg_core.registration.search.config import load_register_config

    path = tmp_path / "config.yaml"
    old = {"search": {**OLD_KEYS, "shaft_rotations": 6}, "inputs": {"seed": 0}}
    path.write_text(yaml.safe_dump(old))
    assert load_register_config(path).search == SearchConfig(shaft_rotations=6)
    assert as_search_config({**OLD_KEYS, "include_coarse": False}) == SearchConfig()


def test_the_search_section_under_its_older_name_is_read_with_one_warning(tmp_path, caplog):
    """``hypotheses:`` (the section's name in earlier registration folders and configs) reads
    as ``search:``, for ``register`` and ``evaluate`` alike, with one warning per file; a file
    with both is refused."""
    import logging

    import yaml

    from comreg_core.evaluation.methods import load_evaluate_config
    from comreg_core.registration.search.config import load_register_config

    old, new = tmp_path / "old.yaml", tmp_path / "new.yaml"
    old.write_text(yaml.safe_dump({"hypotheses": {**OLD_KEYS, "shaft_rotations": 6},
                                   "inputs": {"seed": 0}}))
    new.write_text(yaml.safe_dump({"search": {"shaft_rotations": 6}}))
    with caplog.at_level(logging.WARNING, logger="comreg_core.config"):
        for _ in range(3):
            assert load_register_config(old).search == SearchConfig(shaft_rotations=6)
            assert load_evaluate_config(old).search == SearchConfig(shaft_rotations=6)
        assert load_register_config(new) == load_register_config(old)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "'hypotheses:' is now called 'search:'" in warnings[0]
    off = load_register_config(old, {"search": {"enabled": False}}).search
    assert off == SearchConfig(shaft_rotations=6, enabled=False)
    both = tmp_path / "both.yaml"
    both.write_text(yaml.safe_dump({"hypotheses": {}, "search": {}}))
    with pytest.raises(ConfigError, match="both a 'hypotheses:' and a 'search:' section"):
        load_register_config(both)


@pytest.mark.parametrize("key, value", [
    ("axis_flips", False), ("principal_axes_solve", False), ("retry_ambiguous", False),
    ("polish", False), ("patch_axes", 2), ("patch_axes", 3), ("patch_orientations", 0),
    ("patch_orientations", 12), ("polish", "yes"), ("include_coarse", "no"),
])
def test_removed_options_are_refused_with_a_clear_error(key, value):
    with pytest.raises(ConfigError, match=rf"'search\.{key}' = .* has been removed"):
        as_search_config({key: value})
