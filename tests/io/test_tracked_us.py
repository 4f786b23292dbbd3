"""read_tracked_sweep: which reader a file goes to, and what it refuses."""

from __future__ import annotations

import pytest

from comreg_core.errors import ComRegError
from comreg_core.io.tracked_us import read_tracked_sweep
from tests.helpers import SHARED_DATA

PLUS = SHARED_DATA / "plus"
SPINE_XML = PLUS / "ConfigFiles" / "Testing" / \
    "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
SPINE_VOLUME = PLUS / "TestImages" / "SpinePhantomFreehandReconstructed.mha"
FIBULA_DIR = SHARED_DATA / "ultrabones100k-fibula"


def test_plain_volume_and_wrong_calibration_kind(tmp_path, shared_data):
    with pytest.raises(ComRegError, match="not a PLUS tracked ultrasound sequence"):
        read_tracked_sweep(SPINE_VOLUME)
    with pytest.raises(ComRegError, match="JSON"):
        read_tracked_sweep(FIBULA_DIR, calibration=SPINE_XML)
