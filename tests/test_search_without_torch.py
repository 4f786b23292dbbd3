"""The pose search alone never needs torch: ``Registrar.from_ct`` and ``comreg register --ct``
run in a process where ``import torch`` fails (a CT-only install, or a machine where the torch
build is broken)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import FIBULA_STL

REPO = Path(__file__).resolve().parents[1]

#: Makes every ``import torch`` (and its submodules) raise ImportError in this process.
BLOCK_TORCH = r"""
import sys
class _NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked for this test")
        return None
sys.meta_path.insert(0, _NoTorch())
"""


def _run(code: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", BLOCK_TORCH + code, *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)


def test_torch_is_really_blocked():
    done = _run("import torch")
    assert done.returncode != 0 and "torch is blocked" in done.stderr


def test_the_search_alone_registers_without_torch(shared_data):
    code = r"""
import numpy as np
from comreg_core.io import read_mesh
from comreg_core.register import Registrar
mesh = read_mesh(sys.argv[1])
points = mesh.vertices[mesh.vertices[:, 2] > np.percentile(mesh.vertices[:, 2], 60)]
result = Registrar.from_ct(mesh).register(points)
print(float(np.abs(result.T_ct_us - np.eye(4)).max()))
assert "torch" not in sys.modules
"""
    done = _run(code, str(FIBULA_STL))
    assert done.returncode == 0, done.stderr[-2000:]
    assert float(done.stdout.strip().splitlines()[-1]) < 0.05  # its own surface: identity


def test_comreg_register_with_a_ct_runs_without_torch(shared_data, tmp_path):
    import numpy as np

    from comreg_core.io import PointCloud, read_mesh, write_points

    mesh = read_mesh(FIBULA_STL)
    patch = mesh.vertices[mesh.vertices[:, 2] > np.percentile(mesh.vertices[:, 2], 60)]
    us = write_points(PointCloud(patch, mesh.space), tmp_path / "us.ply")
    code = "from comreg_core.cli import main\nsys.argv[0] = 'comreg'\nmain()\n"
    done = _run(code, "register", str(us), "--ct", str(FIBULA_STL), "--out",
                str(tmp_path / "reg"))
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads((tmp_path / "reg" / "result.json").read_text())
    assert result["verdict"] in ("ok", "check") and result["run_dir"] is None
    assert float(np.abs(np.array(result["T_ct_us"]) - np.eye(4)).max()) < 0.05


@pytest.mark.parametrize("module", ["comreg_core.register", "comreg_core.registration",
                                    "comreg_core.io", "comreg_core.surfaces"])
def test_the_search_side_imports_without_torch(module):
    done = _run(f"import {module}\nassert 'torch' not in sys.modules\n")
    assert done.returncode == 0, done.stderr[-2000:]
