"""Bad input to ``comreg live`` and ``comreg replay``: one ``error:`` line, exit status 2, no
traceback, and nothing connected to or served first; and ``live`` giving up when no server
answers within its connect timeout, with nothing written."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from comreg_core.cli import app
from tests.helpers import FIBULA_STL
from tests.live.conftest import cut_sweep, free_port

REPO = Path(__file__).resolve().parents[2]

runner = CliRunner()


def _refused(args, *contains: str):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert lines[-1].startswith("error: ") and "Traceback" not in result.stderr + result.stdout
    assert sum(line.startswith("error: ") for line in lines) == 1
    for text in contains:
        assert text in lines[-1], (text, lines[-1])


@pytest.fixture(scope="module")
def sweep2(shared_data, tmp_path_factory):
    return cut_sweep(tmp_path_factory.mktemp("sweep2"), 0, 2)


@pytest.mark.parametrize("address", ["nonsense", "127.0.0.1", "127.0.0.1:0", "host:70000",
                                     ":18944", "127.0.0.1:port"])
def test_live_refuses_an_address_that_is_not_host_port(address, tmp_path):
    _refused(["live", "--igtl", address, "--ct", FIBULA_STL, "--out", tmp_path / "out"],
             "is not HOST:PORT")
    assert not (tmp_path / "out").exists()


def test_live_checks_its_inputs_before_connecting(tmp_path):
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", tmp_path / "no.stl"], "does not exist")
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--calibration",
              tmp_path / "no.xml"], "does not exist")
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--verdict-calibration",
              tmp_path / "no.json"], "does not exist")
    (tmp_path / "file").write_text("x")
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--out", tmp_path / "file"],
             "not a folder")
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--image-device", " "],
             "device name is empty")
    # the prior, as 'comreg register' reads it, is read before connecting too
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--init-tolerance", "30,30"],
             "--init-tolerance was given without an initial pose")
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--landmarks",
              tmp_path / "ct.mrk.json", tmp_path / "us.mrk.json"], "does not exist")
    (tmp_path / "ct.mrk.json").write_text("{not json")
    (tmp_path / "us.mrk.json").write_text("{}")
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--landmarks",
              tmp_path / "ct.mrk.json", tmp_path / "us.mrk.json"], "not valid JSON")


def test_replay_refuses_bad_input(sweep2, tmp_path):
    _refused(["replay", tmp_path / "missing"], "does not exist")
    _refused(["replay", sweep2, "--first-frame", "2"], "outside the sweep's 2 frames")
    _refused(["replay", sweep2, "--rate", "0"], "not a positive speed")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        _refused(["replay", sweep2, "--port", taken.getsockname()[1]], "Cannot serve on")
    _refused(["replay", sweep2, "--port", "0", "--wait", "0.2"], "No client connected")


@pytest.mark.parametrize("seconds", ["0", "-1", "nan", "inf"])
def test_live_refuses_a_connect_timeout_that_is_not_a_positive_finite_number(seconds, tmp_path):
    _refused(["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--out", tmp_path / "out",
              "--connect-timeout", seconds], f"--connect-timeout {seconds}",
             "not a positive, finite number")
    assert not (tmp_path / "out").exists()


def test_live_gives_up_when_no_server_answers_and_writes_nothing(tmp_path):
    """Nothing listens on the port: exit 2 and one error line within the timeout (counted from
    the 'listening to' line, after the CT side is prepared) plus a little; --out not made."""
    out, port = tmp_path / "out", free_port()
    live = subprocess.Popen([sys.executable, "-m", "comreg_core.cli", "live", "--igtl",
                             f"127.0.0.1:{port}", "--ct", str(FIBULA_STL), "--out", str(out),
                             "--until-end", "--inline-search", "--connect-timeout", "1.5"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines, listening = [], None
        for line in iter(live.stderr.readline, ""):
            lines.append(line.rstrip("\n"))
            if line.startswith("listening to"):
                listening = time.monotonic()
        live.wait(timeout=60)
        ended = time.monotonic()
        stdout = live.stdout.read()
    finally:
        live.kill()
        live.stdout.close()
        live.stderr.close()
    assert live.returncode == 2, lines
    assert listening is not None and ended - listening < 1.5 + 3.0, lines
    assert lines[-1] == (f"error: No OpenIGTLink server answered at 127.0.0.1:{port} within "
                         "1.5 s (Connection refused). Start PLUS Server (or 'comreg replay') "
                         "there first, check --igtl, or wait longer (--connect-timeout).")
    assert sum(line.startswith("error:") for line in lines) == 1
    assert "Traceback" not in "\n".join(lines) + stdout and stdout == ""
    assert not out.exists()
