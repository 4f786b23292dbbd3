"""The same answer on every machine: a registration gives the same bits whichever BLAS kernels
the CPU gets (``OPENBLAS_CORETYPE``) and whatever CPU numba compiles for (``NUMBA_CPU_NAME``).

Each variant runs in its own process (the kernels are chosen when the libraries load): the
pose search alone on a real 40 mm run of the fibula sweep (a partial sweep of a smooth shaft,
whose flat direction once turned kernel-dependent last bits into poses 1 mm apart) and on the
bundled whole cloud, with a landmark prior too; the digest of every pose and score must match.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

PROGRAM = r"""
import hashlib, sys
import numpy as np
from comreg_core.register import Registrar
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.registration.search.priors import Landmark, Prior
from comreg_core.surfaces.us import extract_us_surface
from tests.helpers import FIBULA_DIR, FIBULA_STL

sweep = read_tracked_sweep(FIBULA_DIR)
us = extract_us_surface(sweep).points
run = us.points[(us.frame_index >= 30) & (us.frame_index < 45)]
registrar = Registrar.from_ct(FIBULA_STL)
digest = hashlib.sha256()
centroid = run.mean(axis=0)
prior = Prior(landmarks=(Landmark("tip", centroid + 5.0, centroid, 20.0),), space="LPS")
for points, given in ((run, None), (run, prior), (us.points[::3], None)):
    result = registrar.register(points, prior=given)
    digest.update(result.T_ct_us.tobytes())
    digest.update(np.float64(result.search.best.score_mm).tobytes())
    digest.update(np.float64(result.search.confidence).tobytes())
print(digest.hexdigest())
"""


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    line = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
    return set(line.split(":", 1)[-1].split())


def _digest(env_changes: dict[str, str], tmp_path: Path) -> str:
    env = {**os.environ, **env_changes, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-c", PROGRAM], env=env, cwd=REPO, timeout=600,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1]


def _blas_variants() -> list[str]:
    """OpenBLAS core types this CPU can run (x86-64 only), the oldest first."""
    if platform.machine() not in ("x86_64", "AMD64"):
        return []
    flags = _cpu_flags()
    variants = ["Nehalem"]
    if "avx2" in flags and "fma" in flags:
        variants.append("Haswell")
    if "avx512f" in flags:
        variants.append("SkylakeX")
    return variants


@pytest.mark.skipif(not _blas_variants(), reason="OpenBLAS core types are named for x86-64")
def test_the_same_bits_with_every_blas_kernel(shared_data, tmp_path):
    digests = {core: _digest({"OPENBLAS_CORETYPE": core}, tmp_path)
               for core in _blas_variants()}
    assert len(set(digests.values())) == 1, digests


@pytest.mark.slow
def test_the_same_bits_with_numba_compiled_for_a_generic_cpu(shared_data, tmp_path):
    """Recompiles every kernel for a generic CPU in a fresh cache (about a minute)."""
    here = _digest({}, tmp_path)
    generic = _digest({"NUMBA_CPU_NAME": "generic",
                       "NUMBA_CACHE_DIR": str(tmp_path / "numba")}, tmp_path)
    assert generic == here
