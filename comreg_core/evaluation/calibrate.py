"""Per-patient calibration of ``p_correct`` (``comreg calibrate``; the end of ``pretrain``).

Simulates short sweeps of the CT (the lengths the user expects; one face, transverse, as the
partial-sweep benchmark's), adds a tracking drift and the real sweeps' point noise, moves each by one of the paper's
random initial poses, registers it with the pose search alone (no network needed: the verdict
judges the pose and the search's competitor, the same with a network), judges it
(:func:`~comreg_core.register.judge.judge`, uncalibrated) and fits
:class:`~comreg_core.registration.judgement.calibration.Calibration` to how its ``p_raw`` maps
to its correctness (within 4 mm / 5 deg of the truth). See
:mod:`comreg_core.registration.judgement.calibration` for the definitions and ``docs/calibration.md``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core import runs
from comreg_core.progress import Progress
from comreg_core.registration.judgement.calibration import Calibration, fit_calibration
from comreg_core.registration.search.priors import DEFAULT_MAX_DEG, DEFAULT_MAX_MM, PRIOR_KINDS

log = logging.getLogger(__name__)

#: Seed namespace of calibration sweeps (disjoint from training and evaluation streams).
CALIBRATION_SEED_NAMESPACE = 0x43414C49
#: Default noise (mm, per coordinate, Gaussian) added to simulated points: the real fibula
#: sweep's points lie a median 0.29 mm from the CT after ICP from their recorded pose, what
#: 0.43 mm of isotropic noise gives (a plane distance's median is 0.674 sigma).
NOISE_MM = 0.43


#: Default tracking error of the simulated frames (RMS over a sweep): a smooth drift of each
#: frame's pose, turned (deg) about and moved (mm) from the sweep's centre. Real sweeps carry
#: it (optical tracking, probe calibration, the hand's pressure); without it simulated sweeps
#: keep their exact shape and the search is right on every one (40 of 40 fibula sweeps), which
#: real sweeps are not (the real fibula's 30-60 mm runs: 27 % of 22). Measured on 16 fibula
#: sweeps of 30-80 mm: drift 1 deg / 1 mm 75 % correct, 1.5 / 1.5 50 %, 2 / 2 12 %.
DRIFT_DEG, DRIFT_MM = 1.5, 1.5
#: Simulated sweeps a calibration registers by default (``comreg calibrate --sweeps``): the
#: map grows stricter with more (on the fibula, OK from ``p_raw`` 0.996 with 40, 0.9996 with 60,
#: 0.9999999995 with 160: 17 of the 52 of 160 sweeps at ``p_raw`` >= 0.95 were wrong,
#: 2026-12-06); ~1.5 s a sweep on an idle 2-core machine.
CALIBRATION_SWEEPS = 60
#: The fewest sweeps a calibration fits its map on.
MIN_SWEEPS = 4
#: What the operating room knows is simulated on each calibration sweep (``comreg calibrate
#: --prior``, one of :data:`PRIOR_KINDS`: nothing, an initial pose or one landmark,
#: :func:`simulated_prior`); a map fitted without a prior under-rates registrations that have
#: one (on the real fibula's runs, 0.26 / 0.63-0.67 predicted / observed below 0.5;
#: docs/calibration.md). The simulated initial pose's largest error (deg, mm: ``--init``'s
#: default tolerances), and the simulated landmark's CT point's error and tolerance (mm):
INIT_DEG, INIT_MM = DEFAULT_MAX_DEG, DEFAULT_MAX_MM
LANDMARK_OFF_MM, LANDMARK_TOLERANCE_MM = 10.0, 15.0


def simulated_prior(rng: np.random.Generator, kind: str, T_true: np.ndarray, moved: np.ndarray,
                    space: str):
    """A :class:`~comreg_core.registration.search.priors.Prior` of ``kind`` around the true
    pose ``T_true`` ``(4, 4)`` of the US points ``moved`` ``(n, 3)``, or None for ``none``:
    ``init``, an initial pose turned by up to :data:`INIT_DEG` (a random axis, the angle
    uniform) and moved by up to :data:`INIT_MM` (a random direction, the length uniform) about
    the placed US centroid, searched within those tolerances; ``landmark``, one of the US points
    paired with its true CT point moved :data:`LANDMARK_OFF_MM` in a random direction, within
    :data:`LANDMARK_TOLERANCE_MM`."""
    import math

    from scipy.spatial.transform import Rotation

    from comreg_core.registration.search.priors import Landmark, Prior
    from comreg_core.transforms import apply_transform

    if kind == "none":
        return None
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    if kind == "landmark":
        us_point = moved[rng.integers(len(moved))]
        ct_point = apply_transform(T_true, us_point[None])[0] + LANDMARK_OFF_MM * direction
        return Prior(landmarks=(Landmark("L1", ct_point, us_point, LANDMARK_TOLERANCE_MM),),
                     space=space)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = Rotation.from_rotvec(axis * math.radians(rng.uniform(0.0, INIT_DEG))).as_matrix()
    centre = apply_transform(T_true, moved.mean(axis=0)[None])[0]
    D = np.eye(4)
    D[:3, :3] = R
    D[:3, 3] = centre - R @ centre + direction * rng.uniform(0.0, INIT_MM)
    return Prior(T_init=D @ T_true, max_deg=INIT_DEG, max_mm=INIT_MM, space=space)


def tracking_drift(points: np.ndarray, slice_index: np.ndarray, rng: np.random.Generator,
                   drift_deg: float = DRIFT_DEG, drift_mm: float = DRIFT_MM) -> np.ndarray:
    """``(n, 3)`` points with each slice's pose drifted: a random walk over the slices, scaled
    to RMS ``drift_deg`` / ``drift_mm``, turning each slice about the sweep's centroid."""
    from scipy.spatial.transform import Rotation

    slices = int(slice_index.max()) + 1
    walk = np.cumsum(rng.normal(size=(slices, 6)), axis=0)
    walk -= walk.mean(axis=0)
    walk /= np.sqrt((walk ** 2).mean(axis=0)).clip(min=1e-12)
    rotations = Rotation.from_rotvec(np.radians(drift_deg) * walk[:, :3] / np.sqrt(3))
    shifts = drift_mm * walk[:, 3:] / np.sqrt(3)
    centre = points.mean(axis=0)
    moved = rotations[slice_index].apply(points - centre) + centre + shifts[slice_index]
    return moved


def calibration_sweep_config(lengths_mm: tuple[float, float]):
    """The simulator's settings for calibration sweeps ``lengths_mm`` long: transverse, over one
    face (the probe's side drifts at most 20 deg), never past the bone's ends."""
    from comreg_core.config import from_dict
    from comreg_core.simulation.config import SimulationConfig

    return from_dict(SimulationConfig, {"trajectory": {
        "length_mm": [float(lengths_mm[0]), float(lengths_mm[1])], "side_drift_deg": 20.0,
        "longitudinal_probability": 0.0, "end_margin_mm": 0.0, "n_slices": [100, 250]}},
        "simulation")


def calibrate(ct_mesh, *, sweeps: int = CALIBRATION_SWEEPS,
              lengths_mm: tuple[float, float] = (30.0, 80.0), noise_mm: float = NOISE_MM,
              drift_deg: float = DRIFT_DEG, drift_mm: float = DRIFT_MM, seed: int = 0,
              progress: Progress | None = None, prior: str = "none") -> Calibration:
    """Register ``sweeps`` simulated sweeps of ``ct_mesh`` (a path or ``(vertices, faces)``)
    and fit the calibration (module docstring); each sweep within a :func:`simulated_prior`
    of kind ``prior`` (:data:`PRIOR_KINDS`), for registrations that will have one.
    Deterministic for a given seed."""
    from comreg_core.errors import ComRegError
    from comreg_core.register import Registrar
    from comreg_core.register.judge import Evidence, judge
    from comreg_core.registration.geometry.metrics import registration_metrics
    from comreg_core.registration.geometry.surface import ct_length_mm
    from comreg_core.registration.judgement.prior_reasons import prior_allows
    from comreg_core.simulation import BoneModel, sample_initial_pose, simulate_sweep
    from comreg_core.surfaces.us_points import beam_origins
    from comreg_core.training.checkpoint import ct_fingerprint
    from comreg_core.transforms import apply_transform, invert_rigid

    if prior not in PRIOR_KINDS:
        raise ComRegError(f"Unknown calibration prior '{prior}'.",
                          f"Use one of {', '.join(PRIOR_KINDS)}.")
    if sweeps < MIN_SWEEPS:
        raise ComRegError(f"A calibration needs at least {MIN_SWEEPS} sweeps, got {sweeps}.", "")
    if not 0 < lengths_mm[0] <= lengths_mm[1]:
        raise ComRegError(f"Sweep lengths {lengths_mm} must be two increasing positive mm.", "")
    registrar = Registrar.from_ct(ct_mesh)
    surface = registrar.surface
    length = ct_length_mm(registrar.search_target(registrar.search_config.target_points))
    bone = BoneModel((surface.vertices, surface.faces))
    config = calibration_sweep_config(lengths_mm)
    raw, correct, rows = [], [], []
    for i in range(sweeps):
        rng = np.random.default_rng([CALIBRATION_SEED_NAMESPACE, seed, i])
        sweep = simulate_sweep(bone, config, rng)
        points = tracking_drift(sweep.points, sweep.slice_index, rng, drift_deg, drift_mm)
        points = points + rng.normal(0.0, noise_mm, points.shape)
        origins = beam_origins(sweep.points, sweep.trajectory.T_ct_image[sweep.slice_index])
        T_p = sample_initial_pose(rng, "paper", surface.bbox_centre)
        moved = apply_transform(T_p, points)
        known = simulated_prior(rng, prior, invert_rigid(T_p), moved, registrar.space)
        result = registrar.register(moved, beam_origins=apply_transform(T_p, origins),
                                    prior=known)
        errors = registration_metrics(result.T_ct_us, invert_rigid(T_p), moved, surface)
        ok = errors["RTE_mm"] < 4.0 and errors["RRE_deg"] < 5.0
        evidence = Evidence.of(result, moved, length,
                               allowed=None if known is None else prior_allows(known, result))
        figures = judge(moved, result.T_ct_us, surface, evidence).figures
        p_raw = figures["p_raw"] if figures["p_raw"] is not None else 0.0
        raw.append(p_raw)
        correct.append(ok)
        rows.append({"p_raw": p_raw, "bound_mm": figures["bound_mm"], "correct": ok,
                     "RTE_mm": errors["RTE_mm"], "RRE_deg": errors["RRE_deg"]})
        if progress is not None:
            progress(i + 1, sweeps, f"calibration sweep {i + 1}/{sweeps}: "
                                    f"{'correct' if ok else 'wrong'}, p_raw {p_raw:.2f}")
    settings: dict[str, Any] = {"lengths_mm": list(lengths_mm), "noise_mm": noise_mm,
                                "drift_deg": drift_deg, "drift_mm": drift_mm,
                                "seed": seed, "perturbation": "paper", "method": "search",
                                "prior": prior}
    calibration = fit_calibration(np.array(raw), np.array(correct),
                                  ct_length_mm=length, settings={**settings, "trials": rows},
                                  ct_fingerprint=ct_fingerprint(surface.vertices, surface.faces))
    log.info("Calibrated on %d simulated sweeps (%.0f %% correct): knots %s", sweeps,
             100 * calibration.correct_share, calibration.knots)
    return calibration


def calibrate_to_directory(ct_mesh, out_dir, **kwargs) -> tuple[Path, Calibration]:
    """:func:`calibrate` and write ``out_dir/calibration.json`` (the folder checked first);
    returns its path and the calibration."""
    from comreg_core.io._files import check_output_folder

    out = check_output_folder(out_dir, inputs=[ct_mesh])
    calibration = calibrate(ct_mesh, **kwargs)
    out.mkdir(parents=True, exist_ok=True)
    return calibration.save(out / runs.CALIBRATION), calibration
