"""The incremental clean-up (comreg_core.surfaces.us_denoise_incremental) against the full one
(``denoise_points`` of all points so far) on the same points: bone points of the real fibula
sweep, with stray echoes and small echo clumps mixed in (clumps kept while they are a fair
share of the largest cluster and dropped once the bone outgrows them), added a few frames at a
time in shuffled order: the same points kept, bit for bit, after every addition."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.surfaces.us_config import DenoiseConfig, USExtractionConfig
from comreg_core.surfaces.us_denoise import denoise_points
from comreg_core.surfaces.us_denoise_incremental import IncrementalDenoise, _local_knn
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints
from tests.helpers import FIBULA_DIR


@pytest.fixture(scope="module")
def frames(shared_data):
    """``{frame: (points (M, 3), scores (M,))}``: the raw bone points of 30 frames of the real
    sweep (frames 10, 20, ...) and, between them, stray echoes and echo clumps."""
    from comreg_core.surfaces.us import extract_us_surface

    sweep = read_tracked_sweep(FIBULA_DIR)
    sweep = replace(sweep, frames=sweep.frames[20:80:2], T_ref_image=sweep.T_ref_image[20:80:2],
                    timestamps=sweep.timestamps[20:80:2], valid=sweep.valid[20:80:2],
                    frame_names=sweep.frame_names[20:80:2])
    raw = extract_us_surface(sweep, USExtractionConfig(denoise=DenoiseConfig(
        cluster_radius_mm=0.0, outlier_neighbors=0))).points
    rng = np.random.default_rng(7)
    out = {}
    for f in np.unique(raw.frame_index):
        here = raw.frame_index == f
        out[10 * int(f) + 10] = (raw.points[here], raw.score[here])
        centre = raw.points[here].mean(axis=0)
        if f % 3 == 0:  # a clump of 6-12 echoes 25-40 mm off the bone
            off = rng.normal(size=3)
            clump = centre + rng.uniform(25, 40) * off / np.linalg.norm(off) \
                + rng.normal(scale=0.6, size=(rng.integers(6, 13), 3))
            out[10 * int(f) + 15] = (clump, rng.uniform(0.1, 1, len(clump)))
        if f % 4 == 1:  # a few stray echoes
            stray = centre + rng.normal(scale=20.0, size=(3, 3))
            out[10 * int(f) + 17] = (stray, rng.uniform(0.1, 1, 3))
    return out


def _full(frames: dict, used: list, config: DenoiseConfig):
    """``denoise_points`` of the frames ``used`` (added in that order), or None."""
    points = np.concatenate([frames[f][0] for f in used])
    index = np.concatenate([np.full(len(frames[f][0]), f) for f in used])
    scores = np.concatenate([frames[f][1] for f in used])
    order = np.argsort(index, kind="stable")
    raw = USSurfacePoints(points[order], index[order], scores[order], len(used), len(used))
    try:
        return denoise_points(raw, config)
    except NoBoneFoundError:
        return None


@pytest.mark.parametrize("config", [DenoiseConfig(),
                                    DenoiseConfig(min_cluster_fraction=0.2, outlier_neighbors=8),
                                    DenoiseConfig(cluster_radius_mm=0.0),
                                    DenoiseConfig(downsample="voxel", voxel_size_mm=1.0)],
                         ids=["default", "fraction0.2-k8", "no-clusters", "voxel"])
def test_the_incremental_clean_up_keeps_the_full_clean_ups_points(frames, config):
    rng = np.random.default_rng(11)
    names = sorted(frames)
    shuffled = [names[i] for i in np.argsort(np.arange(len(names)) + rng.normal(0, 4, len(names)))]
    cleanup, used, checked, dropped_clumps = IncrementalDenoise(config), [], 0, 0
    while len(used) < len(shuffled):
        batch = shuffled[len(used):len(used) + int(rng.integers(1, 5))]
        for f in batch:
            cleanup.add(frames[f][0], np.full(len(frames[f][0]), f), frames[f][1])
        used += batch
        expected = _full(frames, used, config)
        try:
            got = cleanup.cloud(len(used), len(used))
        except NoBoneFoundError:
            got = None
        if expected is None:
            assert got is None
            continue
        assert got.points.shape == expected.points.shape
        assert np.array_equal(got.points, expected.points)  # the same bits
        assert np.array_equal(got.frame_index, expected.frame_index)
        assert np.array_equal(got.score, expected.score)
        assert got.frames_with_bone == expected.frames_with_bone
        assert got.frames_examined == expected.frames_examined
        clumps = {f for f in used if f % 10 == 5}
        dropped_clumps += len(clumps - set(np.unique(got.frame_index).tolist()))
        checked += 1
    assert checked >= 10
    if config.cluster_radius_mm > 0:
        assert dropped_clumps > 0  # the paths that drop points from the selection ran


def test_the_local_neighbour_search_is_the_k_d_trees():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    target = np.concatenate([rng.normal(scale=3.0, size=(400, 3)),
                             rng.normal(scale=60.0, size=(20, 3))])  # a dense blob, far points
    queries = target[rng.choice(len(target), 60, replace=False)]
    expected = cKDTree(target).query(queries, k=17)[0][:, 1:]
    assert np.array_equal(_local_knn(queries, target, 16, 1.0), expected)
