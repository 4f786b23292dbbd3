"""Realism checks: load a real tracked sweep's probe poses and compare trajectory and point-cloud
statistics of real and simulated sweeps.

Only the probe poses of the real sweep are read here (tracking + calibration); its images are not
(bone echoes are extracted elsewhere). The chain, as calibration.json documents it::

    p_ct = T_ct_probe(frame) @ T_probe_image @ diag(sx, sy, 1, 1) @ [col + 0.5, row + 0.5, 0, 1]

so ``T_ct_image = T_ct_probe @ T_probe_image`` maps the image frame in mm (x = col * sx along the
array, y = row * sy into the tissue, row 0 at the transducer face) to CT: the same image frame
as the simulator's slice poses. Euler angles use scipy's ``from_euler('xyz', degrees=True)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from comreg_core.errors import CorruptFileError
from comreg_core.simulation.bone import BoneModel


@dataclass
class TrackedSweepPoses:
    """Probe poses of a real tracked sweep.

    Attributes:
        T_ct_image: ``(N, 4, 4)`` image (mm) to CT pose of each frame.
        timestamps_ms: ``(N,)`` frame timestamps.
        width_mm, depth_mm: image size in mm (lateral, depth).
    """

    T_ct_image: np.ndarray
    timestamps_ms: np.ndarray
    width_mm: float
    depth_mm: float


def load_tracked_sweep_poses(folder: str | Path | None = None, *,
                             tracking_csv: str | Path | None = None,
                             calibration_json: str | Path | None = None) -> TrackedSweepPoses:
    """Read ``tracking.csv`` + ``calibration.json`` (UltraBones100k layout, see the data README)
    from ``folder``, or from the two paths given, with the one frame-folder reader
    (:func:`comreg_core.io.frame_folders.read_frame_folder_tracking`)."""
    from comreg_core.io.frame_folders import read_frame_folder_tracking

    if folder is not None:
        folder = Path(folder)
        tracking_csv = tracking_csv or folder / "tracking.csv"
        calibration_json = calibration_json or folder / "calibration.json"
    if tracking_csv is None or calibration_json is None:
        raise TypeError("give the folder, or both tracking_csv and calibration_json")
    track = read_frame_folder_tracking(tracking_csv, calibration_json)
    if not track.valid.all():
        raise CorruptFileError(tracking_csv, f"{int((~track.valid).sum())} rows have missing or "
                                             "non-numeric pose values")
    sx, sy = track.spacing
    cols, rows = track.image_size
    # The reader puts pixel centres at (c * sx, r * sy); this module's image frame puts them at
    # ((c + 0.5) * sx, (r + 0.5) * sy), as calibration.json does.
    shift = np.eye(4)
    shift[:2, 3] = -0.5 * sx, -0.5 * sy
    return TrackedSweepPoses(track.T_ref_image @ shift, track.timestamps_ms, cols * sx, rows * sy)


def interpolate_poses(T: np.ndarray, factor: int) -> np.ndarray:
    """Insert ``factor - 1`` poses between consecutive ones (linear positions, slerp
    rotations): ``(N, 4, 4)`` -> ``((N - 1) * factor + 1, 4, 4)``. Recovers a sweep recorded
    at every ``factor``-th frame, approximately."""
    T = np.asarray(T, dtype=np.float64)
    n = len(T)
    if factor <= 1 or n < 2:
        return T.copy()
    times = np.arange(n, dtype=np.float64)
    query = np.linspace(0, n - 1, (n - 1) * factor + 1)
    out = np.repeat(np.eye(4)[None], len(query), axis=0)
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(T[:, :3, :3]))(query).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(query, times, T[:, k, 3])
    return out


def trajectory_statistics(bone: BoneModel, T_ct_image: np.ndarray, width_mm: float, *,
                          frame_stride: int = 1, face_samples: int = 21) -> dict[str, np.ndarray]:
    """Per-frame geometry of a sweep relative to the bone's principal axes.

    Returns arrays: ``array_angle_deg`` ``(N,)`` angle of the probe array (image x) to the long
    axis; ``beam_angle_deg`` ``(N,)`` of the beam (image y); ``axial_mm`` ``(N,)`` face-centre
    position along the long axis from the bone's first end; ``advance_mm`` ``(N-1,)`` |axial
    change| per frame (divided by ``frame_stride`` when only every stride-th frame is given);
    ``face_distance_mm`` ``(N,)`` smallest distance from the transducer face (a segment of
    ``face_samples`` points) to the bone surface; ``side_angle_deg`` ``(N,)`` unwrapped angle of
    the face centre about the long axis; and scalar arrays ``coverage`` (fraction of the bone
    length between the extreme face-centre positions) and ``side_span_deg`` (5th-95th
    percentile range of the side angle).
    """
    T = np.asarray(T_ct_image, dtype=np.float64)
    e0, e1, e2 = bone.axes.T
    x, y = T[:, :3, 0], T[:, :3, 1]
    face_centre = T[:, :3, 3] + 0.5 * width_mm * x
    rel = face_centre - bone.centre
    axial = rel @ e0 - bone.axial_range[0]
    ts = np.linspace(0.0, width_mm, face_samples)
    face = T[:, None, :3, 3] + ts[None, :, None] * x[:, None, :]
    distance = bone.distance(face.reshape(-1, 3)).reshape(len(T), -1).min(axis=1)
    side = np.degrees(np.unwrap(np.arctan2(rel @ e2, rel @ e1)))
    covered = np.clip([axial.min(), axial.max()], 0.0, bone.length)
    return {
        "array_angle_deg": np.degrees(np.arccos(np.clip(np.abs(x @ e0), 0, 1))),
        "beam_angle_deg": np.degrees(np.arccos(np.clip(np.abs(y @ e0), 0, 1))),
        "axial_mm": axial,
        "advance_mm": np.abs(np.diff(axial)) / frame_stride,
        "face_distance_mm": distance,
        "side_angle_deg": side,
        "coverage": np.array((covered[1] - covered[0]) / bone.length),
        "side_span_deg": np.array(np.percentile(side, 95) - np.percentile(side, 5)),
    }


def surface_coverage(bone: BoneModel, points: np.ndarray, radius_mm: float = 2.0, *,
                     n_samples: int = 100_000, seed: int = 0) -> float:
    """Fraction of the bone's surface area within ``radius_mm`` of ``(M, 3)`` points (estimated
    with ``n_samples`` area-uniform surface samples)."""
    from scipy.spatial import cKDTree

    samples, _ = bone.sample_surface(n_samples, np.random.default_rng(seed))
    d, _ = cKDTree(np.asarray(points, dtype=np.float64)).query(samples,
                                                                distance_upper_bound=radius_mm)
    return float(np.mean(d <= radius_mm))


def point_spacing(points: np.ndarray, slice_index: np.ndarray, k: int = 16
                  ) -> tuple[float, float]:
    """Median spacing (mm) of a sliced cloud: ``along`` = distance from each point to its
    nearest other point of the same slice; ``across`` = to its nearest point of another slice
    (looked for among the ``k`` nearest neighbours; points with none are skipped)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    slice_index = np.asarray(slice_index)
    d, idx = cKDTree(points).query(points, k=min(k + 1, len(points)))
    d, idx = d[:, 1:], idx[:, 1:]
    same = slice_index[idx] == slice_index[:, None]
    positive = d > 0  # resampled clouds may repeat a point
    along = np.where(same & positive, d, np.inf).min(axis=1)
    across = np.where(~same & positive, d, np.inf).min(axis=1)
    return (float(np.median(along[np.isfinite(along)])),
            float(np.median(across[np.isfinite(across)])))


def summarize(stats: dict[str, np.ndarray]) -> dict[str, float]:
    """Median and 5th/95th percentiles of each per-frame statistic, plus the scalars."""
    out: dict[str, float] = {}
    for key, value in stats.items():
        value = np.asarray(value, dtype=np.float64)
        if value.ndim == 0:
            out[key] = float(value)
        elif key != "axial_mm" and key != "side_angle_deg" and len(value):
            p5, p50, p95 = np.percentile(value, [5, 50, 95])
            out[f"{key}_p5"], out[f"{key}_median"], out[f"{key}_p95"] = p5, p50, p95
    return out


def sweep_statistics(bone: BoneModel, T_ct_image: np.ndarray, points: np.ndarray,
                     slice_index: np.ndarray, width_mm: float, *, frame_stride: int = 1
                     ) -> dict[str, float]:
    """Trajectory summary (:func:`summarize` of :func:`trajectory_statistics`) plus the point
    cloud's ``surface_coverage_2mm`` and ``spacing_along_mm`` / ``spacing_across_mm``
    (:func:`point_spacing`)."""
    out = summarize(trajectory_statistics(bone, T_ct_image, width_mm, frame_stride=frame_stride))
    out["surface_coverage_2mm"] = surface_coverage(bone, points, 2.0)
    out["spacing_along_mm"], out["spacing_across_mm"] = point_spacing(points, slice_index)
    return out


def real_sweep_statistics(bone: BoneModel, poses: TrackedSweepPoses, config=None, *,
                          frame_stride: int = 10, seed: int = 0) -> dict[str, float]:
    """Statistics of a real tracked sweep recorded at every ``frame_stride``-th frame: its
    trajectory, and the point cloud its (interpolated) poses see on the CT bone: a clean replay
    (no drops, no false hits) through the ray caster, resampled to ``config.n_points``. The
    real bone echoes are not used; this measures what the real trajectory covers."""
    from dataclasses import replace

    from comreg_core.simulation.config import ProbeConfig, SimulationConfig
    from comreg_core.simulation.simulator import simulate_from_poses

    config = config or SimulationConfig()
    clean = replace(config, perturbation=replace(config.perturbation, drop_probability=0.0,
                                                 false_hit_probability=0.0),
                    probe=ProbeConfig(poses.width_mm, poses.depth_mm, config.probe.n_rays))
    dense = interpolate_poses(poses.T_ct_image, frame_stride)
    replay = simulate_from_poses(bone, dense, clean, np.random.default_rng(seed))
    out = summarize(trajectory_statistics(bone, poses.T_ct_image, poses.width_mm,
                                          frame_stride=frame_stride))
    out["surface_coverage_2mm"] = surface_coverage(bone, replay.points, 2.0)
    out["spacing_along_mm"], out["spacing_across_mm"] = point_spacing(replay.points,
                                                                      replay.slice_index)
    return out
