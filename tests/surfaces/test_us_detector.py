"""The B-mode bone detector on synthetic frames with a known bone (and on frames without one),
its evidence maps, and its Viterbi path against brute force."""

from __future__ import annotations

import itertools
import logging

import numpy as np
import pytest

from comreg_core.io.sweeps import TrackedSweep
from comreg_core.surfaces.us import extract_us_surface
from comreg_core.surfaces.us_config import BoneDetectorConfig, DenoiseConfig, USExtractionConfig
from comreg_core.surfaces.us_detector import _viterbi, bone_evidence, detect_bone_surface
from comreg_core.surfaces.us_points import NoBoneFoundError
from tests.helpers import assert_close
from tests.surfaces.us_frames import PX, bone_depth, synthetic_frame


def test_detector_finds_a_synthetic_bone():
    rng = np.random.default_rng(0)
    found = detect_bone_surface(synthetic_frame(rng), (PX, PX))
    x = found.cols * PX
    assert np.all((x > 11.0) & (x < 31.0)), "points outside the bone"
    covered = np.isin(np.arange(125, 296), np.round(found.cols).astype(int)).mean()
    assert covered > 0.9
    error = np.abs(found.rows * PX - bone_depth(x))
    assert np.median(error) < 0.1 and np.percentile(error, 95) < 0.3
    assert found.score.min() > BoneDetectorConfig().threshold


def test_evidence_maps_behave_as_documented():
    rng = np.random.default_rng(1)
    ev = bone_evidence(synthetic_frame(rng), (PX, PX))
    assert ev.factor == (1, 1) and ev.probability.shape == (400, 500)
    assert ev.shadow[250, 210] > 0.8 and ev.shadow[250, 450] < 0.3  # under vs beside the bone
    assert ev.tissue[150, 210] > 0.9 and ev.tissue[5, 210] < 0.1  # under tissue vs the gel band
    assert ev.probability[:20].max() == 0  # above min_depth_mm
    coarse = bone_evidence(synthetic_frame(rng), (0.05, 0.05))  # block-averaged 2 x 2
    assert coarse.factor == (2, 2) and coarse.probability.shape == (200, 250)


@pytest.mark.parametrize("kind", ["speckle", "fascia line", "bone without shadow", "black",
                                  "wires in water"])
def test_frames_without_bone_give_no_points(kind):
    rng = np.random.default_rng(2)
    if kind == "black":
        frame = np.zeros((400, 500), np.uint8)
    elif kind == "wires in water":
        frame = np.zeros((400, 500), np.uint8)
        for r, c in [(100, 100), (100, 250), (180, 180), (180, 330)]:
            frame[r - 3:r + 4, c - 8:c + 9] = 200
    else:
        frame = synthetic_frame(rng, bone=kind == "bone without shadow", shadow=False,
                                line=kind == "fascia line")
    assert len(detect_bone_surface(frame, (PX, PX)).rows) == 0


def test_sweep_without_bone_is_a_clear_error_and_partial_bone_a_warning(caplog):
    rng = np.random.default_rng(3)
    frames = np.stack([synthetic_frame(rng, bone=False) for _ in range(3)])
    sweep = TrackedSweep(frames, (PX, PX), np.repeat(np.eye(4)[None], 3, axis=0), [0, 1, 2],
                         [True] * 3)
    with pytest.raises(NoBoneFoundError, match="No bone surface was found in any of the 3"):
        extract_us_surface(sweep)
    frames[0] = synthetic_frame(rng)
    with caplog.at_level(logging.WARNING):
        result = extract_us_surface(sweep, USExtractionConfig(denoise=DenoiseConfig(
            cluster_radius_mm=0, outlier_neighbors=0)))
    assert result.points.frames_with_bone == 1 and "only 1 of 3 frames" in caplog.text
    assert np.all(result.points.frame_index == 0)
    # points land in the reference frame: identity pose, so (x, y) = (col, row) * PX
    assert_close(result.points.points[:, 1], bone_depth(result.points.points[:, 0]), atol=0.3)


def test_viterbi_matches_brute_force():
    """The dynamic programme finds the best path: compared with enumerating every path."""

    def score(path, gain, max_step, step_cost, switch_cost):
        total, previous = 0.0, -1
        for col, row in enumerate(path):
            if row >= 0:
                total += gain[row, col]
                if previous < 0:
                    total -= switch_cost
                elif abs(row - previous) > max_step:
                    return -np.inf
                else:
                    total -= step_cost * abs(row - previous)
            elif previous >= 0:
                total -= switch_cost
            previous = row
        return total - (switch_cost if previous >= 0 else 0.0)

    rng = np.random.default_rng(4)
    for _ in range(150):
        h, w = int(rng.integers(1, 4)), int(rng.integers(1, 6))
        gain = rng.normal(0, 1, (h, w))
        args = (int(rng.integers(1, 3)), float(rng.uniform(0, 1)), float(rng.uniform(0, 1)))
        best = max(score(p, gain, *args) for p in itertools.product(range(-1, h), repeat=w))
        assert_close(score(_viterbi(gain, *args), gain, *args), best, atol=1e-9)


def _numpy_viterbi(gain: np.ndarray, max_step: int, step_cost: float, switch_cost: float
             ) -> np.ndarray:
    """Best path through the columns of ``gain`` ``(h, w)`` (reward of "bone at row r in column
    c"; "no bone" earns 0). Moving between bone rows r -> r' in neighbouring columns costs
    ``step_cost * |r - r'|`` and is allowed for ``|r - r'| <= max_step``; entering or leaving
    bone costs ``switch_cost``. Returns ``(w,)`` rows, -1 where there is no bone. The numpy code
    the compiled ``_viterbi`` replaced: its reference."""
    h, w = gain.shape
    shifts = np.arange(-max_step, max_step + 1)
    source = np.arange(h)[:, None] + shifts[None, :]  # (h, S): candidate previous rows
    inside = (source >= 0) & (source < h)
    source = np.clip(source, 0, h - 1)
    penalty = np.where(inside, step_cost * np.abs(shifts)[None, :], np.inf)
    back = np.empty((w, h), dtype=np.int32)  # previous bone row, or -1 = came from "no bone"
    off_from = np.full(w, -1, dtype=np.int32)  # row the "no bone" state left bone at, or -1
    v_bone = gain[:, 0].astype(np.float64) - switch_cost
    v_off = 0.0
    rows = np.arange(h)
    for col in range(1, w):
        cand = v_bone[source] - penalty
        best = np.argmax(cand, axis=1)
        stay = cand[rows, best]
        enter = v_off - switch_cost
        from_bone = stay >= enter
        back[col] = np.where(from_bone, source[rows, best], -1)
        top = int(np.argmax(v_bone))
        leave = v_bone[top] - switch_cost
        new_off = v_off
        if leave > v_off:
            new_off, off_from[col] = leave, top
        v_bone = np.where(from_bone, stay, enter) + gain[:, col]
        v_off = new_off
    path = np.full(w, -1, dtype=np.int64)
    top = int(np.argmax(v_bone))
    in_bone = v_bone[top] - switch_cost > v_off
    row = top
    for col in range(w - 1, -1, -1):
        if in_bone:
            path[col] = row
            previous = int(back[col, row]) if col > 0 else -1
            if previous < 0:
                in_bone = False
            else:
                row = previous
        elif col > 0 and off_from[col] >= 0:
            in_bone, row = True, int(off_from[col])
    return path


def test_compiled_viterbi_matches_the_numpy_code_it_replaced():
    """Path for path, on 300 random problems (a fifth of them with tied gains) and float32 /
    float64 gains."""
    rng = np.random.default_rng(0)
    for trial in range(300):
        h, w = int(rng.integers(5, 60)), int(rng.integers(2, 60))
        gain = rng.normal(size=(h, w)) * 3 * rng.random()
        gain = np.round(gain) if trial % 5 == 0 else gain
        gain = gain.astype(np.float32 if trial % 2 else np.float64)
        args = (int(rng.integers(0, 5)), float(rng.random()), float(3 * rng.random()))
        np.testing.assert_array_equal(_viterbi(gain, *args), _numpy_viterbi(gain, *args))
