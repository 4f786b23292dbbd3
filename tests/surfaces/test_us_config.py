"""Loading and validating the ultrasound extraction settings."""

from __future__ import annotations

import pytest

from comreg_core.config import ConfigError
from comreg_core.surfaces.us_config import (BoneDetectorConfig, DenoiseConfig,
                                            load_us_extraction_config)


def test_config_loading_and_validation(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("detector:\n  threshold: 0.2\n  max_depth_mm: 30\nframe_step: 2\n")
    config = load_us_extraction_config(path)
    assert config.detector.threshold == 0.2 and config.detector.max_depth_mm == 30.0
    assert config.frame_step == 2 and config.denoise == DenoiseConfig()
    path.write_text("detector:\n  treshold: 0.2\n")
    with pytest.raises(ConfigError, match="treshold"):
        load_us_extraction_config(path)
    with pytest.raises(ConfigError, match="threshold"):
        BoneDetectorConfig(threshold=1.5)
    with pytest.raises(ConfigError, match="target_points"):
        DenoiseConfig(downsample="fps")
    with pytest.raises(ConfigError, match="frame_step"):
        load_us_extraction_config(overrides={"frame_step": 0})
