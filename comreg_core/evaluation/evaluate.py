"""The evaluation harness: random initial poses, any registration methods, paper metrics,
``metrics.json``. Independent of the network: a method is any callable.

Protocol of one trial ``k`` (for a cloud ``S`` in its US frame, ground truth ``T_gt = T_ct_us``,
identity unless given):

1. ``T_p = sample_initial_pose(rng_k, perturbation, center=c)`` with ``c`` the CT mesh's
   bounding-box centre (the centre the network normalises about) and ``rng_k`` the trial's own
   generator (:func:`evaluation_rng`); ``T_p`` is a misalignment expressed in the CT frame.
2. The method receives ``S_k = T_p @ T_gt (S)``: the cloud put into its true place, then moved
   by ``T_p``. So the misalignment relative to the CT follows the sampler's distribution (as in
   training) whatever ``T_gt`` is, and the trial's ground truth is ``T_ct_us_k = T_p^-1``.
3. The method returns an estimate of ``T_ct_us_k`` (see :func:`evaluate` for what it may
   return); the metrics of :mod:`.metrics` compare it with ``T_p^-1``. ``initial_RTE_mm`` and
   ``initial_RRE_deg`` are the same metrics for the identity (doing nothing).

``metrics.json`` (:func:`write_metrics`)::

    {"settings": {...},
     "trials": [{"trial": 0, "method": "ransac", "cloud": 0, "RTE_mm": .., "RRE_deg": ..,
                 "CD_mm": .., "HD95_mm": .., "completion_CD_mm": null, "completion_HD95_mm": null,
                 "runtime_s": .., "wall_s": .., "success": true, "flip": false,
                 "initial_RTE_mm": .., "initial_RRE_deg": .., "T_ct_us": [[..] x4],
                 "T_ct_us_gt": [[..] x4], "confidence": null, "ambiguous": null, "error": null,
                 "info": {..}}, ...],
     "summary": {"<method>": {"RTE_mm": {"mean": .., "std": .., "median": ..}, "RRE_deg": {..},
                 "CD_mm": {..}, "HD95_mm": {..}, "completion_CD_mm": {..},
                 "completion_HD95_mm": {..}, "runtime_s": {..}, "success_rate": ..,
                 "flip_rate": .., "ambiguous_rate": .., "unflagged_flip_rate": ..,
                 "trials": .., "failures": ..}}}

Rates are fractions in [0, 1] of *all* trials of the method (a failed trial is neither a success
nor a flip). ``confidence`` and ``ambiguous`` are the method's own verdict on its result (ComReg
with its pose search, :mod:`comreg_core.registration.search.search`; null for methods without one);
``ambiguous_rate`` is the share of trials flagged ambiguous and ``unflagged_flip_rate`` the share
that are flips *not* flagged (silent flips), both null for a method that flags nothing. Statistics (numpy mean, population std with ``ddof=0``, median) are over the trials
with a value; ``null`` where there is none (e.g. completion metrics of a method without a
completion). A method that raises :class:`~comreg_core.errors.ComRegError` (or returns an
unusable transform) fails that trial: its row has ``"error"`` and ``null`` metrics. Any other
exception is a bug and propagates.

Seeds: every random stream of an evaluation comes from
``SeedSequence(seed, spawn_key=(EVALUATION_SEED_NAMESPACE, stream, index))``. Training and
validation sweeps come from :func:`~comreg_core.simulation.sweep_rng` (``spawn_key=(index,)``) or
any spawn key not starting with the namespace, so evaluation clouds and poses never share a
random stream with them, even when the same integer seed is used for both (SeedSequence hashes
the seed *and* the spawn key into its state).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core.progress import Progress
from comreg_core.config import ConfigError
from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.io.json_files import strict_json, write_json
from comreg_core.registration.geometry.metrics import (DEFAULT_CT_SAMPLES, as_surface,
                                                       completion_metrics, registration_metrics,
                                                       rotation_error_deg, translation_error_mm)
from comreg_core.evaluation.outputs import as_registration_output
from comreg_core.transforms import apply_transform, as_points, check_rigid, invert_rigid

log = logging.getLogger(__name__)

#: First spawn-key word of every evaluation random stream (ASCII "EVAL").
EVALUATION_SEED_NAMESPACE = 0x4556414C
#: Stream numbers below the namespace.
STREAM_CLOUDS, STREAM_POSES = 0, 1
PERTURBATIONS = ("paper", "full")
#: The metrics summarised with mean/std/median, in output order.
SUMMARY_METRICS = ("RTE_mm", "RRE_deg", "CD_mm", "HD95_mm", "completion_CD_mm",
                   "completion_HD95_mm", "runtime_s")


def evaluation_rng(seed: int, stream: int, index: int) -> np.random.Generator:
    """The generator of item ``index`` of evaluation stream ``stream`` (:data:`STREAM_CLOUDS`,
    :data:`STREAM_POSES`) for ``seed``; disjoint from every training stream (module docstring)."""
    return np.random.default_rng(np.random.SeedSequence(
        _seed(seed), spawn_key=(EVALUATION_SEED_NAMESPACE, int(stream), int(index))))


def _seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"The seed must be a non-negative integer, got {seed!r}.",
                          "Pass --seed 0 or another whole number.")
    return int(seed)


def simulated_us_clouds(ct_mesh, count: int, seed: int = 0, config=None) -> list[np.ndarray]:
    """``count`` fresh simulated US sweeps of ``ct_mesh`` (``(n_points, 3)`` mm each, CT frame).

    Sweep ``i`` uses ``evaluation_rng(seed, STREAM_CLOUDS, i)``: independent of ``count`` and
    disjoint from the training streams (see the module docstring). ``config`` is a
    :class:`~comreg_core.simulation.SimulationConfig` (default: the paper's simulation).
    """
    from comreg_core.simulation import BoneModel, simulate_sweep

    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ConfigError(f"The number of simulated clouds must be a positive integer, got "
                          f"{count!r}.", "Pass 1 or more.")
    if isinstance(ct_mesh, BoneModel):
        bone = ct_mesh
    else:
        surface = as_surface(ct_mesh)
        bone = BoneModel((surface.vertices, surface.faces))
    return [simulate_sweep(bone, config, evaluation_rng(seed, STREAM_CLOUDS, i)).points
            for i in range(int(count))]


def _clouds(us_points) -> list[np.ndarray]:
    from comreg_core.io.pointclouds import PointCloud

    if isinstance(us_points, (np.ndarray, PointCloud)):
        items = [us_points]
    elif isinstance(us_points, Sequence) and not isinstance(us_points, str):
        items = list(us_points)
        # a nested list of coordinates is one cloud; a list of arrays/clouds is several
        if items and not isinstance(items[0], (np.ndarray, PointCloud)) and np.ndim(items[0]) <= 1:
            items = [us_points]
    else:
        raise InvalidGeometryError(
            f"Cannot use a {type(us_points).__name__} as the US points.",
            "Pass an (N, 3) array, a PointCloud, a list of them, or 'simulated'.")
    if not items:
        raise InvalidGeometryError("No US clouds were given.", "Pass at least one cloud.")
    clouds = []
    for i, item in enumerate(items):
        what = "US points" if len(items) == 1 else f"US points of cloud {i}"
        pts = as_points(item.points if isinstance(item, PointCloud) else item, what)
        if len(pts) < 3:
            raise InvalidGeometryError(f"The {what} have {len(pts)} points; registration needs "
                                       "at least 3.", "Pass a larger cloud.")
        clouds.append(pts)
    return clouds


def _check_methods(methods) -> dict[str, Callable]:
    if not isinstance(methods, Mapping) or not methods:
        raise ComRegError("No registration methods to evaluate.",
                          "Pass a dict {name: callable}, e.g. from baseline_methods(['ransac']).")
    for name, method in methods.items():
        if not isinstance(name, str) or not name:
            raise ComRegError(f"Method name {name!r} is not a non-empty string.",
                              "Name every method, e.g. 'comreg', 'ransac', 'icp-gt'.")
        if not callable(method):
            raise ComRegError(f"Method '{name}' is a {type(method).__name__}, not callable.",
                              "Pass a function or object taking the (N, 3) US points.")
    return dict(methods)


def evaluate(methods: Mapping[str, Callable], us_points, ct_mesh, *, trials: int,
             seed: int = 0, perturbation: str = "paper", T_gt: np.ndarray | None = None,
             simulation_config=None, n_ct_samples: int = DEFAULT_CT_SAMPLES,
             progress: Progress | None = None) -> dict[str, Any]:
    """Register ``trials`` randomly moved copies of the US cloud(s) with every method.

    Args:
        methods: ``{name: method}``. ``method(points)`` gets the ``(N, 3)`` moved cloud (mm) and
            returns a :class:`~comreg_core.evaluation.outputs.RegistrationOutput`, an object or
            dict with ``T_ct_us`` (4x4) and optionally ``runtime_s`` (else the wall time),
            ``completion`` (``(M, 3)`` in the received cloud's frame) or ``completion_ct`` (CT
            frame under its own estimate), ``info``; or a bare 4x4 array. A method with the
            attribute ``needs_ground_truth = True`` (the ``icp-gt`` pseudo ground truth) is
            called as ``method(points, T_ct_us_gt=truth)``.
        us_points: one ``(N, 3)`` array or :class:`~comreg_core.io.PointCloud` (in the space of
            the CT mesh), a list of them (trial ``k`` uses cloud ``k % len``), or ``"simulated"``:
            ``trials`` fresh sweeps from :func:`simulated_us_clouds` (ground truth identity).
        ct_mesh: the CT surface (path, SurfaceMesh, BoneModel, trimesh, (V, F) or
            :class:`~comreg_core.registration.geometry.surface.CTSurface`).
        trials: number of random initial poses (>= 1).
        seed: seeds the poses (and simulated clouds); the same seed gives the same trials.
        perturbation: ``"paper"`` (one axis, +-90 deg, +-100 mm) or ``"full"`` (any axis, up to
            180 deg and 500 mm); see :mod:`comreg_core.simulation.poses`.
        T_gt: ``(4, 4)`` ground-truth ``T_ct_us`` of the given cloud(s); identity if None.
        simulation_config: SimulationConfig for ``"simulated"``.
        n_ct_samples: CT samples of the completion metrics.
        progress: called as ``progress(done, total)`` after each method call.

    Returns:
        The ``metrics.json`` dict (module docstring); write it with :func:`write_metrics`.
    """
    methods = _check_methods(methods)
    if isinstance(trials, bool) or not isinstance(trials, (int, np.integer)) or trials < 1:
        raise ConfigError(f"The number of trials must be a positive integer, got {trials!r}.",
                          "Pass --trials 1 or more.")
    seed = _seed(seed)
    if perturbation not in PERTURBATIONS:
        raise ConfigError(f"Unknown perturbation '{perturbation}'.",
                          f"Use one of: {', '.join(PERTURBATIONS)}.")
    T_gt = np.eye(4) if T_gt is None else check_rigid(T_gt)
    surface = as_surface(ct_mesh)
    if isinstance(us_points, str):
        if us_points != "simulated":
            raise ComRegError(f"US points '{us_points}' is not understood.",
                              "Pass an (N, 3) array, a list of clouds, or the word 'simulated'.")
        if not np.allclose(T_gt, np.eye(4)):
            raise ComRegError("A ground-truth transform was given for simulated clouds.",
                              "Simulated clouds are already in the CT frame; drop --gt.")
        clouds = simulated_us_clouds(surface, int(trials), seed, simulation_config)
        source = "simulated"
    else:
        clouds = _clouds(us_points)
        source = f"{len(clouds)} given cloud(s)"
    centre = surface.bbox_centre
    from comreg_core.simulation import sample_initial_pose

    rows: list[dict[str, Any]] = []
    total, done = int(trials) * len(methods), 0
    for k in range(int(trials)):
        cloud_index = k % len(clouds)
        T_p = sample_initial_pose(evaluation_rng(seed, STREAM_POSES, k), perturbation, centre)
        moved = apply_transform(T_p @ T_gt, clouds[cloud_index])
        truth = invert_rigid(T_p)
        c = moved.mean(axis=0)
        initial = {"initial_RTE_mm": translation_error_mm(np.eye(4), truth, c),
                   "initial_RRE_deg": rotation_error_deg(np.eye(4), truth)}
        for name, method in methods.items():
            rows.append(_trial(k, name, method, moved, truth, cloud_index, surface, initial,
                               n_ct_samples))
            done += 1
            if progress is not None:
                progress(done, total)
    settings = {"trials": int(trials), "seed": seed, "perturbation": perturbation,
                "us_points": source, "T_gt": T_gt.tolist(), "methods": list(methods),
                "ct_mesh": str(surface.path) if surface.path else None,
                "rotation_centre_mm": centre.tolist(), "n_ct_samples": int(n_ct_samples),
                "seed_namespace": EVALUATION_SEED_NAMESPACE}
    return {"settings": settings, "trials": rows, "summary": summarize(rows, list(methods))}


def _trial(k, name, method, moved, truth, cloud_index, surface, initial, n_ct_samples):
    row: dict[str, Any] = {"trial": k, "method": name, "cloud": cloud_index}
    row.update({m: None for m in ("RTE_mm", "RRE_deg", "CD_mm", "HD95_mm", "completion_CD_mm",
                                  "completion_HD95_mm", "runtime_s", "wall_s")})
    row.update(success=False, flip=False, **initial, T_ct_us=None, T_ct_us_gt=truth.tolist(),
               confidence=None, ambiguous=None, error=None, info={})
    t0 = time.perf_counter()
    try:
        if getattr(method, "needs_ground_truth", False):
            result = method(moved.copy(), T_ct_us_gt=truth.copy())
        else:
            result = method(moved.copy())
        wall = time.perf_counter() - t0
        out = as_registration_output(result, wall)
    except ComRegError as exc:
        log.warning("Trial %d: method '%s' failed: %s", k, name, exc)
        row.update(wall_s=time.perf_counter() - t0, error=str(exc))
        return row
    row.update(registration_metrics(out.T_ct_us, truth, moved, surface))
    if out.completion is not None:
        row.update(completion_metrics(out.completion, truth, surface, n_ct_samples=n_ct_samples))
    row.update(runtime_s=out.runtime_s, wall_s=wall, T_ct_us=out.T_ct_us.tolist(),
               confidence=out.confidence, ambiguous=out.ambiguous, info=strict_json(out.info)[0])
    log.info("Trial %d %s: RTE %.2f mm, RRE %.2f deg, %.2f s", k, name, row["RTE_mm"],
             row["RRE_deg"], out.runtime_s)
    return row


def _stats(values: list) -> dict[str, float | None]:
    vals = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if len(vals) == 0:
        return {"mean": None, "std": None, "median": None}
    return {"mean": float(vals.mean()), "std": float(vals.std()),
            "median": float(np.median(vals))}


def summarize(rows: list[dict[str, Any]], methods: list[str] | None = None) -> dict[str, Any]:
    """The ``summary`` part of ``metrics.json`` from the per-trial ``rows``."""
    methods = methods or list(dict.fromkeys(r["method"] for r in rows))
    summary = {}
    for name in methods:
        mine = [r for r in rows if r["method"] == name]
        entry: dict[str, Any] = {m: _stats([r[m] for r in mine]) for m in SUMMARY_METRICS}
        n = len(mine)
        entry["success_rate"] = sum(bool(r["success"]) for r in mine) / n if n else None
        entry["flip_rate"] = sum(bool(r["flip"]) for r in mine) / n if n else None
        flags = [r.get("ambiguous") for r in mine]
        if n and any(f is not None for f in flags):
            entry["ambiguous_rate"] = sum(bool(f) for f in flags) / n
            entry["unflagged_flip_rate"] = sum(bool(r["flip"]) and not r.get("ambiguous")
                                               for r in mine) / n
        else:
            entry["ambiguous_rate"] = entry["unflagged_flip_rate"] = None
        entry["trials"] = n
        entry["failures"] = sum(r["error"] is not None for r in mine)
        summary[name] = entry
    return summary


def write_metrics(result: dict[str, Any], path: str | Path) -> Path:
    """Write the :func:`evaluate` result as strict JSON, atomically: NaN/inf as null, with
    ``null_reasons`` (:func:`comreg_core.io.json_files.write_json`)."""
    return write_json(result, path)


def summary_line(summary: dict) -> str:
    """One line of a method's evaluation summary (``comreg evaluate`` prints it); "n/a" where no trial gave a value."""
    def number(value, fmt: str) -> str:
        return "n/a" if value is None else format(value, fmt)

    flagged = "" if summary["ambiguous_rate"] is None else (
        f", flagged ambiguous {number(summary['ambiguous_rate'], '.1%')} (unflagged flips "
        f"{number(summary['unflagged_flip_rate'], '.1%')})")
    failures = f", {summary['failures']} failed" if summary.get("failures") else ""
    return (f"success {number(summary['success_rate'], '.1%')}, flips "
            f"{number(summary['flip_rate'], '.1%')}, median RTE "
            f"{number(summary['RTE_mm']['median'], '.2f')} mm, median RRE "
            f"{number(summary['RRE_deg']['median'], '.2f')} deg, mean runtime "
            f"{number(summary['runtime_s']['mean'], '.2f')} s{flagged}{failures}")
