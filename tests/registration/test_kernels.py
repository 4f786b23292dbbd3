"""The compiled kernels of the pose search (comreg_core/registration/geometry/kernels.py) against the
numpy code they replaced (tests/registration/reference.py: the same update and closest points),
the Python ICP loop and score (the screening's), scipy's rotations; and the same output at 1
and 2 threads."""

import numba
import numpy as np
from scipy.spatial.transform import Rotation

from comreg_core.registration.geometry import kernels, mesh_kernels
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import point_to_plane_icp, strided
from comreg_core.registration.search.scoring import score_poses
from tests.helpers import random_rigid
from tests.registration.reference import closest_points_on_triangles, numpy_pose_steps


def _starts(rng, points, count, degrees=25.0, mm=15.0):
    """``(count, 4, 4)`` poses up to ``degrees``/``mm`` from the identity about the centroid."""
    centre = points.mean(axis=0)
    T = np.tile(np.eye(4), (count, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(count, 3)) * np.radians(degrees) / 2
                                        ).as_matrix()
    T[:, :3, 3] = centre - T[:, :3, :3] @ centre + rng.uniform(-mm, mm, size=(count, 3))
    return T


def test_rotation_from_rotvec_matches_scipy():
    rng = np.random.default_rng(0)
    vectors = np.concatenate([rng.normal(size=(50, 3)), rng.normal(size=(50, 3)) * 1e-5,
                              np.zeros((1, 3))])
    for v in vectors:
        R = np.empty((3, 3))
        kernels._rotation_from_rotvec(v, R)
        np.testing.assert_allclose(R, Rotation.from_rotvec(v).as_matrix(), atol=1e-14)


def test_select_is_the_kth_smallest():
    rng = np.random.default_rng(1)
    for n in (1, 2, 7, 64, 65, 200):
        for trial in range(50):
            values = (rng.integers(0, 4, n).astype(float) if trial % 2 else rng.normal(size=n))
            k = int(rng.integers(0, n))
            assert kernels._select(values.copy(), n, k) == np.sort(values)[k]


def test_pose_steps_match_the_numpy_update():
    rng = np.random.default_rng(2)
    m, n = 5, 40
    moved, q = rng.normal(size=(m, n, 3)) * 20, rng.normal(size=(m, n, 3)) * 20
    nrm = rng.normal(size=(m, n, 3))
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    d = np.linalg.norm(moved - q, axis=2)
    d[0, :10] = np.inf  # unmatched pairs
    d[1, 3:] = np.inf  # too few pairs: no update
    for trim in (0.0, 0.1, 0.3):
        T_numpy = np.tile(random_rigid(rng), (m, 1, 1))
        T_compiled = T_numpy.copy()
        expected = numpy_pose_steps(moved, q, nrm, d, trim, T_numpy)
        got = kernels.pose_steps(moved, q, nrm, d, trim, T_compiled)
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12, equal_nan=True)
        np.testing.assert_allclose(T_compiled, T_numpy, rtol=0, atol=1e-9)
        assert np.isnan(got[1, 0]) and (T_compiled[1] == T_numpy[1]).all()


def test_grid_icp_and_scores_match_the_python_screening(fibula_patch, fibula_surface):
    target = fibula_surface.cloud(5000)
    config = SearchConfig()
    rng = np.random.default_rng(4)
    starts = _starts(rng, fibula_patch, 40, degrees=40.0, mm=30.0)
    src = strided(fibula_patch, 64)
    expected = point_to_plane_icp(src, starts, target.match_approx, iterations=20,
                                  trim_fraction=0.1, tolerance_mm=0.1)
    origin, spacing, grid = target.closest_point_grid
    poses, rmse, done = kernels.grid_icp(src, starts, origin, float(spacing), grid,
                                         target.points, target.normals, 20, 0.1, 0.1)
    np.testing.assert_allclose(poses, expected.T, atol=1e-6)
    np.testing.assert_array_equal(done, expected.iterations)
    np.testing.assert_allclose(rmse, expected.rmse_mm, rtol=1e-6)

    sub = strided(fibula_patch, 128)
    origins = sub + 40.0 * np.array([0.0, 0.0, 1.0])  # beams from one side: some face away
    for beam_origins in (None, origins):
        expected_scores = score_poses(poses, sub, target, config, approximate=True,
                                      origins=beam_origins)
        scores = kernels.grid_scores(poses, sub, np.zeros((0, 3)) if beam_origins is None
                                     else beam_origins, origin, float(spacing), grid,
                                     target.points, target.normals, config.score_trim,
                                     config.facing_penalty_mm)
        np.testing.assert_allclose(scores, expected_scores, rtol=1e-9)
    assert (np.abs(scores - expected_scores) < 1e-9).all() and scores.max() > 1.0


def test_kernels_give_the_same_bits_at_one_and_two_threads(fibula_patch, fibula_surface):
    target = fibula_surface.cloud(5000)
    starts = _starts(np.random.default_rng(5), fibula_patch, 64, degrees=60.0, mm=40.0)
    origin, spacing, grid = target.closest_point_grid
    src = strided(fibula_patch, 64)
    outputs = []
    before = numba.get_num_threads()
    try:
        for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(threads)
            outputs.append(kernels.grid_icp(src, starts, origin, float(spacing), grid,
                                            target.points, target.normals, 20, 0.1, 0.1))
    finally:
        numba.set_num_threads(before)
    for a, b in zip(*outputs):
        np.testing.assert_array_equal(a, b)


def test_closest_on_candidates_matches_the_numpy_voronoi_tests(fibula_surface):
    """Exact closest points on candidate triangles: the kernel against
    the reference closest_points_on_triangles on points near, on and far from the mesh (every
    Voronoi region: vertices, edges, faces)."""

    rng = np.random.default_rng(6)
    vertices, faces = fibula_surface.vertices, fibula_surface.faces
    points = vertices[rng.integers(0, len(vertices), 300)] + rng.normal(size=(300, 3)) * 3.0
    candidates = rng.integers(0, len(faces), size=(300, 8))
    closest, face, dist = mesh_kernels.closest_on_candidates(points, candidates, vertices, faces)
    tri = vertices[faces[candidates]]
    q = closest_points_on_triangles(points[:, None], tri[..., 0, :], tri[..., 1, :],
                                    tri[..., 2, :])
    dq = np.linalg.norm(q - points[:, None], axis=2)
    best = np.argmin(dq, axis=1)
    rows = np.arange(len(points))
    np.testing.assert_allclose(dist, dq[rows, best], atol=1e-9)
    np.testing.assert_allclose(closest, q[rows, best], atol=1e-9)
    np.testing.assert_array_equal(face, candidates[rows, best])
    serial = mesh_kernels.closest_on_candidates_serial(points, candidates, vertices, faces)
    for parallel, alone in zip((closest, face, dist), serial):  # the same numbers, bit for bit
        np.testing.assert_array_equal(parallel, alone)


#: Run in a fresh process (kernels other tests called are compiled already): the compiled
#: kernels of comreg_core that no other kernel calls (those are compiled into their callers),
#: with or without a compiled signature after the set-up's compile functions.
_ENTRY_POINTS = """
import importlib, inspect, json, pkgutil, re
import comreg_core
from numba.core.registry import CPUDispatcher
from comreg_core.registration.geometry.kernels import compile_kernels
from comreg_core.registration.judgement.uncertainty_kernels import compile_uncertainty_kernels
from comreg_core.live.igtl import crc64

compile_kernels()
compile_uncertainty_kernels()
crc64(b"ComReg")
found = {}
for info in pkgutil.walk_packages(comreg_core.__path__, "comreg_core."):
    if not info.name.endswith("__main__"):
        module = importlib.import_module(info.name)
        found.update({f"{info.name}.{name}": obj for name, obj in vars(module).items()
                      if isinstance(obj, CPUDispatcher) and obj.__module__ == info.name})
sources = {key: inspect.getsource(kernel.py_func) for key, kernel in found.items()}
called = {key for key in found for other, source in sources.items()
          if other != key and re.search(rf"\\b{key.rsplit('.', 1)[1]}\\(", source)}
print(json.dumps({key: bool(found[key].signatures) for key in sorted(set(found) - called)}))
"""


def test_the_set_up_compiles_every_kernel_python_calls():
    """``compile_kernels``, ``compile_uncertainty_kernels`` and a first ``crc64`` (live's;
    scripts/setup-env.sh calls all three) leave no kernel for the first registration, detection, live update or volume to
    compile."""
    import json
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _ENTRY_POINTS], capture_output=True, text=True,
                         check=True)
    compiled = json.loads(run.stdout.strip().splitlines()[-1])
    assert len(compiled) >= 20, compiled  # measured: 25
    assert [name for name, done in compiled.items() if not done] == []
