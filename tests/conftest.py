import os

import pytest

from tests.helpers import SHARED_DATA

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")


@pytest.fixture(scope="session")
def shared_data():
    """Path to ../shared/data; the real recorded data every test run must have."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"Real test data not found at {SHARED_DATA}: clone the project beside shared/.")
    return SHARED_DATA
