"""Fixtures of the live-registration tests: frame folders cut from the real UltraBones100k
fibula sweep (so the replay reads a real recording through ``read_tracked_sweep``), and a free
loopback port per test."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from tests.helpers import FIBULA_STL, cut_sweep

def free_port() -> int:
    """A port nobody listens on now (the OS's choice for a bound, then closed socket)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture(scope="session")
def ct_stl(shared_data) -> Path:
    return FIBULA_STL


@pytest.fixture(scope="session")
def sweep12(shared_data, tmp_path_factory) -> Path:
    """The first 12 frames of the real sweep (every other one: 24 frames' length of bone)."""
    return cut_sweep(tmp_path_factory.mktemp("sweep12"), 0, 12, step=2)


@pytest.fixture(scope="session")
def search_registrar(shared_data):
    """The pose search on the fibula CT, prepared once for the session's tests."""
    from comreg_core.register import Registrar

    return Registrar.from_ct(FIBULA_STL)
