"""``SimulationConfig``: every knob of the US sweep simulator, with the paper's values as defaults.

Three sections plus output settings (YAML keys in brackets):

- ``probe``: the linear-array image geometry (defaults from the real UltraBones100k frames:
  950 x 811 px at 0.05392 mm = 51.2 mm wide, 43.7 mm deep).
- ``trajectory``: how sweeps are laid out on the bone (from its principal axes): transverse or
  longitudinal, slice count, coverage, probe side, skin distance.
- ``perturbation``: the paper's stochastic perturbations (tilt random walk, lognormal sweep
  speed, dropped slices, false intersections), with the paper's values.

Angles are degrees in the config (keys end in ``_deg``) and radians inside the code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from comreg_core.config import from_dict, load_config, require


def _require_range(value: tuple, name: str, lo: float, hi: float, *, strict: bool = False):
    a, b = value
    require(lo <= a <= hi and lo <= b <= hi, name, f"must lie in [{lo}, {hi}], got {list(value)}")
    if strict:
        require(a < b, name, f"needs min < max, got {list(value)}")
    else:
        require(a <= b, name, f"needs min <= max, got {list(value)}")


@dataclass(frozen=True)
class ProbeConfig:
    """Linear-array probe: the image is ``width_mm`` wide (lateral, image x) and ``depth_mm`` deep
    (beam, image y); ``n_rays`` parallel rays, one per lateral position, start at the face.

    Set them to the probe (and depth setting) that records the real sweeps: the simulated
    images should cover what the real ones do (the defaults are UltraBones100k's)."""

    width_mm: float = 51.2
    depth_mm: float = 43.7
    n_rays: int = 256

    def __post_init__(self):
        require(1.0 <= self.width_mm <= 200.0, "probe.width_mm", "must lie in [1, 200] mm")
        require(1.0 <= self.depth_mm <= 300.0, "probe.depth_mm", "must lie in [1, 300] mm")
        require(2 <= self.n_rays <= 4096, "probe.n_rays", "must lie in [2, 4096]")


@dataclass(frozen=True)
class TrajectoryConfig:
    """Sweep layout, relative to the bone's principal axes (PCA of its surface).

    The defaults spread sweeps over the whole bone and every side. Set them to how the real
    sweeps are taken, so that the network trains on what it will see: e.g. short sweeps over
    one face (``length_mm: [40, 50]``, ``side_drift_deg: 20``, ``longitudinal_probability:
    0``: ``comreg evaluate --config``, ``tests/benchmarks/bench_partial.py``).

    Attributes:
        longitudinal_probability: chance a sweep is longitudinal (array along the long axis,
            probe moved across the bone); otherwise transverse (array across the long axis, probe
            moved along it, as in the real data).
        n_slices: inclusive range of the slice count N of one sweep.
        coverage_fraction: range of a transverse sweep's length as a fraction of bone length.
        length_mm: range of a transverse sweep's length in mm instead (e.g. ``[30, 60]`` for
            the short sweeps of intraoperative US; with ``side_drift_deg`` small and
            ``longitudinal_probability: 0``, a short sweep over one face); null = use
            ``coverage_fraction``.
        end_margin_mm: a transverse sweep may run this far past either bone end.
        longitudinal_width_mm: range of a longitudinal sweep's lateral travel.
        direction_jitter_deg: variation of the global sweep direction: the probe array is turned
            about the beam by up to +-j from perpendicular (transverse) or parallel
            (longitudinal) to the long axis (a bounded walk like the side angle's).
        side_angle_deg: range of the starting side angle about the long axis, measured from
            ``side_reference`` (a CT-frame direction, projected normal to the long axis) or, if
            that is unset, from the second principal axis. Together with ``side_reference``:
            when only one face of the bone can be scanned (the approach of a procedure), say
            which, e.g. ``side_reference: [0, -1, 0]`` (anterior, in an LPS mesh),
            ``side_angle_deg: [-30, 30]`` and a small ``side_drift_deg``; the second principal
            axis points in no anatomical direction.
        side_drift_deg: total range the side angle may drift within one sweep (bounded walk).
        face_distance_mm: range of the transducer-face-to-bone distance (bounded walk).
        lateral_offset_mm: the bone's centre may sit up to this far off the image centre.
        drift_step: random-walk step (std) per slice of side angle, face distance, lateral
            offset and array turn, as a fraction of each one's allowed range.
        drift_window: moving-average window applied to those walks.
    """

    longitudinal_probability: float = 0.2
    n_slices: tuple[int, int] = (200, 500)
    coverage_fraction: tuple[float, float] = (0.5, 1.0)
    length_mm: Optional[tuple[float, float]] = None
    end_margin_mm: float = 20.0
    longitudinal_width_mm: tuple[float, float] = (15.0, 40.0)
    direction_jitter_deg: float = 10.0
    side_angle_deg: tuple[float, float] = (0.0, 360.0)
    side_reference: Optional[tuple[float, float, float]] = None
    side_drift_deg: float = 90.0
    face_distance_mm: tuple[float, float] = (7.0, 27.0)
    lateral_offset_mm: float = 8.0
    drift_step: float = 0.05
    drift_window: int = 25

    def __post_init__(self):
        require(0.0 <= self.longitudinal_probability <= 1.0, "trajectory.longitudinal_probability",
                "must lie in [0, 1]")
        _require_range(self.n_slices, "trajectory.n_slices", 2, 100_000)
        _require_range(self.coverage_fraction, "trajectory.coverage_fraction", 0.01, 2.0)
        if self.length_mm is not None:
            _require_range(self.length_mm, "trajectory.length_mm", 1.0, 2000.0)
        require(0.0 <= self.end_margin_mm <= 200.0, "trajectory.end_margin_mm",
                "must lie in [0, 200] mm")
        _require_range(self.longitudinal_width_mm, "trajectory.longitudinal_width_mm", 0.1, 500.0)
        require(0.0 <= self.direction_jitter_deg <= 90.0, "trajectory.direction_jitter_deg",
                "must lie in [0, 90]")
        _require_range(self.side_angle_deg, "trajectory.side_angle_deg", -360.0, 720.0)
        require(self.side_angle_deg[1] - self.side_angle_deg[0] <= 360.0,
                "trajectory.side_angle_deg", "must span at most 360 degrees")
        if self.side_reference is not None:
            require(any(abs(v) > 0 for v in self.side_reference), "trajectory.side_reference",
                    "must be a non-zero direction (or null)")
        require(0.0 <= self.side_drift_deg <= 360.0, "trajectory.side_drift_deg",
                "must lie in [0, 360]")
        _require_range(self.face_distance_mm, "trajectory.face_distance_mm", 0.0, 200.0)
        require(0.0 <= self.lateral_offset_mm <= 100.0, "trajectory.lateral_offset_mm",
                "must lie in [0, 100] mm")
        require(0.0 <= self.drift_step <= 1.0, "trajectory.drift_step", "must lie in [0, 1]")
        require(1 <= self.drift_window <= 10_000, "trajectory.drift_window",
                "must lie in [1, 10000]")


@dataclass(frozen=True)
class PerturbationConfig:
    """The paper's perturbations (section 2), paper values as defaults.

    Change them to match the real sweeps of a site (a steadier or shakier hand, a tracker's
    dropouts, a detector's false echoes): :mod:`comreg_core.simulation.realism` measures the
    same statistics on a real tracked sweep and on simulated ones
    (``tests/benchmarks/bench_simulation.py`` prints them side by side).

    Attributes:
        tilt_x_max_deg, tilt_y_max_deg: bounds |theta_x|max, |theta_y|max of the per-slice tilts;
            theta_x turns the probe about its array (lateral) axis, fanning the image plane along
            the sweep; theta_y about its elevation axis, rocking the image in its own plane.
        tilt_window: moving-average window w_theta applied to the bounded random walk.
        tilt_step: std of one random-walk step as a fraction of the bound.
        speed_sigma: sigma_s of the lognormal step multipliers.
        speed_window: moving-average window w_s applied to the step noise.
        speed_clip: (f_min, f_max) clip of the multipliers.
        speed_noise: "mean" applies MA_ws as a plain moving average (the paper's formula, to the
            letter: the smoothed noise has std 1/sqrt(w_s), so multipliers stay within about
            exp(+-0.5)); "standardized" rescales the smoothed noise to unit variance (multipliers
            then use most of the clip range). The two readings of the paper's formula; set
            "standardized" for sweeps as uneven as the real one: the real fibula sweep's advance
            per frame spans p5-p95 ratio ~50, "mean" gives ~2-3, "standardized" within a factor
            4 of it (``tests/simulation/test_realism.py``). "mean" stays the default: the paper.
        drop_probability: chance that a slice is dropped (produces no points).
        false_hit_probability: chance per ray of a false intersection (segmentation noise).
        false_hit_neighbors: a false intersection also replaces the result of this many
            neighbouring rays on each side (same slice, same depth).
        false_hit_depth: range of a false hit's depth as a fraction of the image depth.
    """

    tilt_x_max_deg: float = 20.0
    tilt_y_max_deg: float = 5.0
    tilt_window: int = 25
    tilt_step: float = 0.1
    speed_sigma: float = 1.8
    speed_window: int = 61
    speed_clip: tuple[float, float] = (0.03, 10.0)
    speed_noise: Literal["mean", "standardized"] = "mean"
    drop_probability: float = 0.05
    false_hit_probability: float = 0.003
    false_hit_neighbors: int = 1
    false_hit_depth: tuple[float, float] = (0.1, 0.9)

    def __post_init__(self):
        require(0.0 <= self.tilt_x_max_deg <= 89.0, "perturbation.tilt_x_max_deg",
                "must lie in [0, 89]")
        require(0.0 <= self.tilt_y_max_deg <= 89.0, "perturbation.tilt_y_max_deg",
                "must lie in [0, 89]")
        require(1 <= self.tilt_window <= 10_000, "perturbation.tilt_window",
                "must lie in [1, 10000]")
        require(0.0 <= self.tilt_step <= 1.0, "perturbation.tilt_step", "must lie in [0, 1]")
        require(0.0 <= self.speed_sigma <= 10.0, "perturbation.speed_sigma", "must lie in [0, 10]")
        require(1 <= self.speed_window <= 10_000, "perturbation.speed_window",
                "must lie in [1, 10000]")
        _require_range(self.speed_clip, "perturbation.speed_clip", 1e-6, 1e6)
        require(self.speed_clip[0] <= 1.0 <= self.speed_clip[1], "perturbation.speed_clip",
                "must contain 1 (f_min <= 1 <= f_max)")
        require(0.0 <= self.drop_probability < 1.0, "perturbation.drop_probability",
                "must lie in [0, 1)")
        require(0.0 <= self.false_hit_probability <= 1.0, "perturbation.false_hit_probability",
                "must lie in [0, 1]")
        require(0 <= self.false_hit_neighbors <= 64, "perturbation.false_hit_neighbors",
                "must lie in [0, 64]")
        _require_range(self.false_hit_depth, "perturbation.false_hit_depth", 0.0, 1.0)


@dataclass(frozen=True)
class SimulationConfig:
    """The whole simulator.

    Attributes:
        mode: "sweep" (ray-cast US sweeps, the paper's method) or "uniform" (area-uniform samples
            of the CT surface: the paper's ablation, AdaPoinTr's sampling; Table 3).
        n_points: points per output cloud (the paper uses 20,000; the ``cpu`` preset 2048).
        uniform_keep_fraction: in "uniform" mode, keep only this fraction of the surface nearest
            to a random viewpoint (AdaPoinTr-style partial crop); 1.0 keeps the whole surface.
            For the ablation with partial inputs as AdaPoinTr makes them (its crops keep the
            part of the shape nearest a random viewpoint) instead of whole-surface samples.
        min_hits: a sweep that yields fewer raw points is redrawn (up to ``max_attempts``).
            Lower it for a small bone or a narrow probe, whose sweeps rarely hit it 200 times.
        max_attempts: redraws before giving up with a SimulationError.
    """

    mode: Literal["sweep", "uniform"] = "sweep"
    n_points: int = 20_000
    uniform_keep_fraction: float = 1.0
    min_hits: int = 200
    max_attempts: int = 20
    probe: ProbeConfig = field(default_factory=ProbeConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    perturbation: PerturbationConfig = field(default_factory=PerturbationConfig)

    def __post_init__(self):
        require(1 <= self.n_points <= 10_000_000, "n_points", "must lie in [1, 10000000]")
        require(0.0 < self.uniform_keep_fraction <= 1.0, "uniform_keep_fraction",
                "must lie in (0, 1]")
        require(1 <= self.min_hits <= 10_000_000, "min_hits", "must lie in [1, 10000000]")
        require(1 <= self.max_attempts <= 1000, "max_attempts", "must lie in [1, 1000]")


def simulation_config_from_dict(data: dict | None) -> SimulationConfig:
    """Build a SimulationConfig from a mapping: either its own keys, or a file written by
    :func:`comreg_core.simulation.simulate_to_directory` (keys ``simulation`` and ``run``; ``run``
    is ignored)."""
    data = dict(data or {})
    if "simulation" in data:
        data = data["simulation"] or {}
    return from_dict(SimulationConfig, data, "simulation")


def load_simulation_config(path: str | Path | None = None,
                           overrides: dict | None = None) -> SimulationConfig:
    """Defaults, updated from the YAML file at ``path`` (bare keys, or a run's ``config.yaml``
    with a ``simulation`` section), then from ``overrides``."""
    return load_config(SimulationConfig, path, overrides, section="simulation")
