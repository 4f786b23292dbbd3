"""Ray-cast US sweep simulation: trajectory -> rays -> first hits (acoustic shadowing) -> noise ->
fixed-size point cloud in the CT frame, with a per-point slice index."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from comreg_core.progress import Progress
from comreg_core.errors import ComRegError
from comreg_core.simulation.bone import BoneModel
from comreg_core.simulation.config import SimulationConfig
from comreg_core.simulation.processes import dropped_slices, false_hits
from comreg_core.simulation.trajectory import SweepTrajectory, ray_grid, sample_trajectory

log = logging.getLogger(__name__)


class SimulationError(ComRegError):
    """The simulator could not produce a usable sweep (e.g. the probe never sees the bone)."""


@dataclass
class SimulatedSweep:
    """One simulated US bone point cloud.

    Attributes:
        points: ``(M, 3)`` float64 mm, CT frame (the mesh's coordinates).
        slice_index: ``(M,)`` int64 slice each point comes from (-1 in "uniform" mode).
        ray_index: ``(M,)`` int64 ray (lateral position) within the slice (-1 in "uniform").
        is_false: ``(M,)`` bool, false intersections (segmentation noise).
        trajectory: the sweep's :class:`SweepTrajectory` (None in "uniform" mode).
        n_rays_cast: rays cast (kept slices x rays per slice).
        n_false_events: false-intersection events drawn (each affects up to 2k+1 rays).
    """

    points: np.ndarray
    slice_index: np.ndarray
    ray_index: np.ndarray
    is_false: np.ndarray
    trajectory: SweepTrajectory | None
    n_rays_cast: int = 0
    n_false_events: int = 0

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, index: np.ndarray) -> "SimulatedSweep":
        """The sweep restricted to points ``index`` (an int or bool array)."""
        return replace(self, points=self.points[index], slice_index=self.slice_index[index],
                       ray_index=self.ray_index[index], is_false=self.is_false[index])


def cast_sweep(bone: BoneModel, trajectory: SweepTrajectory, config: SimulationConfig,
               rng: np.random.Generator) -> SimulatedSweep:
    """Cast every ray of the kept slices in one embree call, keep the first hit of each ray, and
    add false intersections. Returns all raw points (not resampled), ordered by slice then ray.
    Each ray reports at most one point: its first hit within the image depth, or a false hit."""
    probe, pc = config.probe, config.perturbation
    kept = np.flatnonzero(~trajectory.dropped)
    origins, directions = ray_grid(trajectory.T_ct_image[kept], probe.width_mm, probe.n_rays)
    shape = origins.shape[:2]
    face, points = bone.cast(origins.reshape(-1, 3), directions.reshape(-1, 3), probe.depth_mm)
    face, points = face.reshape(shape), points.reshape(shape + (3,))
    events, affected, depth = false_hits(len(kept), probe.n_rays, pc.false_hit_probability,
                                         pc.false_hit_neighbors, pc.false_hit_depth, rng)
    if affected.any():
        points[affected] = (origins[affected]
                            + (depth[affected] * probe.depth_mm)[:, None] * directions[affected])
    valid = (face >= 0) | affected
    rows, cols = np.nonzero(valid)
    return SimulatedSweep(points[rows, cols], kept[rows].astype(np.int64), cols.astype(np.int64),
                          affected[rows, cols], trajectory, n_rays_cast=int(valid.size),
                          n_false_events=int(events.sum()))


def resample(sweep: SimulatedSweep, n_points: int, rng: np.random.Generator) -> SimulatedSweep:
    """Exactly ``n_points`` points: a random subset without replacement if there are enough,
    otherwise every point once plus random repeats. Order is kept (slice, then ray)."""
    m = len(sweep)
    if m == 0:
        raise SimulationError("The sweep has no points to resample.",
                              "Check the mesh and the probe settings.")
    if m >= n_points:
        index = np.sort(rng.choice(m, n_points, replace=False))
    else:
        index = np.sort(np.concatenate([np.arange(m), rng.choice(m, n_points - m)]))
    return sweep.subset(index)


def simulate_sweep(bone: BoneModel, config: SimulationConfig | None = None,
                   rng: np.random.Generator | None = None, *, resample_points: bool = True
                   ) -> SimulatedSweep:
    """One synthetic US bone point cloud of ``bone`` (``config.mode`` "sweep" or "uniform").

    A sweep whose rays hit the bone fewer than ``config.min_hits`` times is redrawn, up to
    ``config.max_attempts`` times (then :class:`SimulationError`). With ``resample_points`` the
    cloud has exactly ``config.n_points`` points; without it, every raw point.
    """
    config = config or SimulationConfig()
    rng = rng if rng is not None else np.random.default_rng()
    if config.mode == "uniform":
        return sample_uniform(bone, config, rng)
    for attempt in range(config.max_attempts):
        trajectory = sample_trajectory(bone, config, rng)
        raw = cast_sweep(bone, trajectory, config, rng)
        true_hits = int((~raw.is_false).sum())
        if true_hits >= config.min_hits:
            return resample(raw, config.n_points, rng) if resample_points else raw
        log.debug("Sweep attempt %d hit the bone %d times (< %d); redrawing", attempt,
                  true_hits, config.min_hits)
    raise SimulationError(
        f"No simulated sweep hit the bone at least {config.min_hits} times in "
        f"{config.max_attempts} attempts.",
        "Check that the mesh is the bone in millimetres and that probe.depth_mm and "
        "trajectory.face_distance_mm leave the bone inside the image; or lower min_hits.")


def simulate_from_poses(bone: BoneModel, T_ct_image: np.ndarray,
                        config: SimulationConfig | None = None,
                        rng: np.random.Generator | None = None, *,
                        resample_points: bool = True) -> SimulatedSweep:
    """Replay given slice poses ``(N, 4, 4)`` (image frame of :mod:`.trajectory`): no trajectory
    perturbations, but dropped slices and false hits as ``config.perturbation`` says (set their
    probabilities to 0 for a clean replay)."""
    config = config or SimulationConfig()
    rng = rng if rng is not None else np.random.default_rng()
    from comreg_core.transforms import check_rigid

    T = np.asarray(T_ct_image, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise SimulationError(f"Slice poses must have shape (N, 4, 4), got {T.shape}.",
                              "Pass one 4x4 image-to-CT matrix per slice.")
    for pose in T:
        check_rigid(pose)
    dropped = dropped_slices(len(T), config.perturbation.drop_probability, rng)
    raw = cast_sweep(bone, SweepTrajectory.replay(T, dropped), config, rng)
    if not (~raw.is_false).any():
        raise SimulationError("None of the given probe poses sees the bone.",
                              "Check that the poses and the mesh are in the same frame (mm).")
    return resample(raw, config.n_points, rng) if resample_points else raw


def sample_uniform(bone: BoneModel, config: SimulationConfig, rng: np.random.Generator
                   ) -> SimulatedSweep:
    """The paper's ablation: ``n_points`` area-uniform samples of the CT surface; with
    ``uniform_keep_fraction < 1`` only that fraction nearest a random viewpoint is kept
    (AdaPoinTr-style crop)."""
    n = config.n_points
    keep = config.uniform_keep_fraction
    total = n if keep >= 1.0 else int(np.ceil(n / keep))
    points, _ = bone.sample_surface(total, rng)
    if total > n:
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        viewpoint = bone.centre + direction * bone.length
        nearest = np.argsort(np.linalg.norm(points - viewpoint, axis=1), kind="stable")[:n]
        points = points[np.sort(nearest)]
    minus = np.full(n, -1, dtype=np.int64)
    return SimulatedSweep(points, minus, minus.copy(), np.zeros(n, bool), None)


def sweep_rng(seed: int, index: int) -> np.random.Generator:
    """The Generator of sweep ``index`` of a run with ``seed``: independent streams, and sweep i
    is the same whatever the number of sweeps."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index,)))


def simulate_sweeps(mesh, count: int, seed: int, config: SimulationConfig | None = None,
                    progress: Progress | None = None) -> list[SimulatedSweep]:
    """``count`` sweeps of ``mesh`` (anything :class:`BoneModel` accepts, or a BoneModel)."""
    bone = mesh if isinstance(mesh, BoneModel) else BoneModel(mesh)
    sweeps = []
    for i in range(count):
        sweeps.append(simulate_sweep(bone, config, sweep_rng(seed, i)))
        if progress is not None:
            progress(i + 1, count)
    return sweeps


def simulate_to_directory(ct_mesh_path: str | Path, out_dir: str | Path, *, count: int = 1,
                          seed: int | None = 0,
                          config: SimulationConfig | str | Path | None = None,
                          progress: Progress | None = None) -> list[Path]:
    """Simulate ``count`` sweeps of the CT bone mesh and write them to ``out_dir``.

    Files (``i`` = 0000, 0001, ...; every file written atomically):

    - ``sweep_i.ply``: the ``(n_points, 3)`` cloud in mm, in the mesh file's space
      (``SPACE=`` comment, as the mesh declared it).
    - ``sweep_i_slices.npy``: int32 ``(n_points,)`` slice index of each point (-1 in uniform
      mode).
    - ``sweep_i_poses.npy``: float64 ``(N, 4, 4)`` ``T_ct_image`` of every slice of the sweep
      (image x lateral, y depth, z elevation, mm); dropped slices are NaN. Sweep mode only.
    - ``config.yaml`` (last): ``simulation:`` the config used and ``run:`` mesh path, count,
      seed and file names; it can be passed back as ``--config``.

    ``config`` is a SimulationConfig, a YAML file for :func:`load_simulation_config` (what
    ``--config FILE`` passes), or None for the defaults. The same seed gives byte-identical
    files; sweep i does not depend on ``count``. With ``seed=None`` a fresh seed is drawn and
    recorded. Files of an earlier run in ``out_dir`` are overwritten, never deleted. Returns the
    point-cloud paths.
    """
    import yaml

    from comreg_core.config import ConfigError, to_dict
    from comreg_core.io._files import atomic_output, check_output_folder
    from comreg_core.io.meshes import read_mesh
    from comreg_core.io.pointclouds import PointCloud, write_points

    out_dir = check_output_folder(out_dir, inputs=[ct_mesh_path] + (
        [config] if isinstance(config, (str, Path)) else []))
    if isinstance(config, (str, Path)):
        from comreg_core.simulation.config import load_simulation_config

        config = load_simulation_config(config)
    config = config or SimulationConfig()
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ConfigError(f"The sweep count must be a positive integer, got {count!r}.",
                          "Pass --count 1 or more.")
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % (2**63))
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"The seed must be a non-negative integer, got {seed!r}.",
                          "Pass --seed 0 or another whole number.")
    mesh = read_mesh(ct_mesh_path)
    bone = BoneModel(mesh)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths, names = [], []
    for i in range(int(count)):
        sweep = simulate_sweep(bone, config, sweep_rng(int(seed), i))
        stem = f"sweep_{i:04d}"
        cloud_path = write_points(PointCloud(sweep.points, mesh.space), out_dir / f"{stem}.ply")
        _save_npy(out_dir / f"{stem}_slices.npy", sweep.slice_index.astype(np.int32))
        names += [cloud_path.name, f"{stem}_slices.npy"]
        if sweep.trajectory is not None:
            poses = sweep.trajectory.T_ct_image.copy()
            poses[sweep.trajectory.dropped] = np.nan
            _save_npy(out_dir / f"{stem}_poses.npy", poses)
            names.append(f"{stem}_poses.npy")
        paths.append(cloud_path)
        if progress is not None:
            progress(i + 1, int(count))
    record = {"simulation": to_dict(config),
              "run": {"ct_mesh": str(Path(ct_mesh_path).resolve()), "count": int(count),
                      "seed": int(seed), "files": names}}
    with atomic_output(out_dir / "config.yaml") as tmp:
        tmp.write_text(yaml.safe_dump(record, sort_keys=False), encoding="utf-8")
    log.info("Wrote %d simulated sweeps to %s", count, out_dir)
    return paths


def _save_npy(path: Path, array: np.ndarray) -> None:
    from comreg_core.io._files import atomic_output

    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)
