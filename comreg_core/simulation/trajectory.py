"""Sweep trajectories drawn from the bone's own geometry (never from recorded tracking).

Image frame (as in calibration.json of the real data, in mm): origin at the transducer face's
first element edge, x along the array (0..width), y along the beam into the tissue (0..depth),
z = x cross y (elevation). A slice pose is ``T_ct_image`` ``(4, 4)``: ``T_ct_image @ p_image``.

A transverse sweep (array across the long axis, probe moved along it, like the real data) and a
longitudinal sweep (array along the long axis, probe moved across the bone) are both laid out in
the bone's principal frame (e0 long axis, e1, e2): the probe looks at the bone from the side
``u(phi) = cos(phi) e1 + sin(phi) e2``, its face ``d`` mm above the bone surface in that
direction, the array centred over the bone's cross-section (plus an offset). Side angle, face
distance and offset drift slowly along the sweep (bounded random walks + moving average); the
paper's perturbations (tilts, non-uniform speed, dropped slices) come from
:mod:`comreg_core.simulation.processes`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comreg_core.simulation.bone import BoneModel
from comreg_core.simulation.config import SimulationConfig
from comreg_core.simulation.processes import (dropped_slices, moving_average, reflected_walk,
                                              slice_positions, smoothed_bounded_walk)

#: Extra axial half-thickness (mm) of the bone slab used to place a transverse probe.
_ELEVATION_MARGIN_MM = 2.0


@dataclass
class SweepTrajectory:
    """The probe path of one sweep, N slices.

    Attributes:
        kind: "transverse", "longitudinal" or "replay" (poses given by the caller).
        T_ct_image: ``(N, 4, 4)`` slice poses (image frame in the module docstring).
        dropped: ``(N,)`` bool, slices that produce no points.
        positions: ``(N,)`` slice positions s_i (mm) along the sweep direction, monotone from
            s_min to s_max (NaN for replays).
        multipliers: ``(N-1,)`` step multipliers m_i (empty for replays).
        tilt_x, tilt_y: ``(N,)`` radians: theta_x about the array axis (image x), theta_y about
            the elevation axis (image z); zeros for replays.
        twist: ``(N,)`` radians, turn of the array about the beam (variation of the global sweep
            direction: a slow bounded walk within +-direction_jitter_deg).
        side_angle: ``(N,)`` radians, face_distance ``(N,)`` mm, lateral_offset ``(N,)`` mm.
        R_base: ``(N, 3, 3)`` orientation before twist and tilts (columns image x, y, z).
    """

    kind: str
    T_ct_image: np.ndarray
    dropped: np.ndarray
    positions: np.ndarray
    multipliers: np.ndarray
    tilt_x: np.ndarray
    tilt_y: np.ndarray
    twist: np.ndarray
    side_angle: np.ndarray
    face_distance: np.ndarray
    lateral_offset: np.ndarray
    R_base: np.ndarray

    @property
    def n_slices(self) -> int:
        return len(self.T_ct_image)

    @classmethod
    def replay(cls, T_ct_image: np.ndarray, dropped: np.ndarray | None = None
               ) -> "SweepTrajectory":
        """A trajectory that replays given ``(N, 4, 4)`` slice poses as they are."""
        T = np.asarray(T_ct_image, dtype=np.float64)
        n = len(T)
        nan = np.full(n, np.nan)
        return cls("replay", T, np.zeros(n, bool) if dropped is None else np.asarray(dropped),
                   nan, np.zeros(0), np.zeros(n), np.zeros(n), np.zeros(n), nan, nan, nan,
                   T[:, :3, :3].copy())


def _rot_x(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1),
                     np.stack([z, s, c], -1)], -2)


def _rot_y(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1),
                     np.stack([-s, z, c], -1)], -2)


def _rot_z(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def _drift(n: int, lo: float, hi: float, start: float, step_fraction: float, window: int,
           rng: np.random.Generator) -> np.ndarray:
    walk = reflected_walk(n, lo, hi, step_fraction * (hi - lo), start, rng)
    return moving_average(walk, window)


def _side_reference_angle(bone: BoneModel, reference) -> float:
    if reference is None:
        return 0.0
    r = np.asarray(reference, dtype=np.float64)
    e = bone.axes
    return float(np.arctan2(r @ e[:, 2], r @ e[:, 1]))


def sample_trajectory(bone: BoneModel, config: SimulationConfig, rng: np.random.Generator
                      ) -> SweepTrajectory:
    """Draw one sweep trajectory over ``bone`` (all per-slice geometry vectorised)."""
    tc, pc, probe = config.trajectory, config.perturbation, config.probe
    n = int(rng.integers(tc.n_slices[0], tc.n_slices[1] + 1))
    longitudinal = bool(rng.random() < tc.longitudinal_probability)
    sign = 1.0 if rng.random() < 0.5 else -1.0  # direction of travel
    flip = bool(rng.random() < 0.5)  # probe held either way round (marker left or right)
    a_min, a_max = bone.axial_range
    if longitudinal:
        width = rng.uniform(*tc.longitudinal_width_mm)
        quarter = min(probe.width_mm / 4, bone.length / 2)
        axial_centre = rng.uniform(a_min + quarter, a_max - quarter)
        s_min, s_max = -width / 2, width / 2
    else:
        lo, hi = a_min - tc.end_margin_mm, a_max + tc.end_margin_mm
        length = (rng.uniform(*tc.coverage_fraction) * bone.length if tc.length_mm is None
                  else rng.uniform(*tc.length_mm))
        length = min(length, hi - lo)
        start = rng.uniform(lo, hi - length)
        s_min, s_max = (start, start + length) if sign > 0 else (-start - length, -start)
    positions, multipliers = slice_positions(
        n, s_min, s_max, sigma=pc.speed_sigma, window=pc.speed_window, clip=pc.speed_clip,
        rng=rng, noise=pc.speed_noise)
    tilt_x = smoothed_bounded_walk(n, np.radians(pc.tilt_x_max_deg), pc.tilt_step,
                                   pc.tilt_window, rng)
    tilt_y = smoothed_bounded_walk(n, np.radians(pc.tilt_y_max_deg), pc.tilt_step,
                                   pc.tilt_window, rng)
    jitter = np.radians(tc.direction_jitter_deg)
    twist = _drift(n, -jitter, jitter, rng.uniform(-jitter, jitter), tc.drift_step,
                   tc.drift_window, rng)
    side0 = np.radians(rng.uniform(*tc.side_angle_deg))
    half_drift = np.radians(tc.side_drift_deg) / 2
    side = (_side_reference_angle(bone, tc.side_reference) + side0
            + _drift(n, -half_drift, half_drift, rng.uniform(-half_drift, half_drift),
                     tc.drift_step, tc.drift_window, rng))
    d_lo, d_hi = tc.face_distance_mm
    distance = _drift(n, d_lo, d_hi, rng.uniform(d_lo, d_hi), tc.drift_step, tc.drift_window,
                      rng)
    off = tc.lateral_offset_mm
    offset = _drift(n, -off, off, rng.uniform(-off, off), tc.drift_step, tc.drift_window, rng)
    dropped = dropped_slices(n, pc.drop_probability, rng)

    e0, e1, e2 = bone.axes.T
    u = np.cos(side)[:, None] * e1 + np.sin(side)[:, None] * e2  # (N, 3) towards the probe
    lateral = np.cross(e0, u)  # (N, 3)
    if longitudinal:
        axial = np.full(n, axial_centre)
        height = bone.support(axial, side, probe.width_mm / 2)
        across = (np.einsum("ij,ij->i", bone.section_centre(axial), lateral) + offset
                  + sign * positions)
        x_axis = np.broadcast_to(e0, (n, 3))
    else:
        axial = sign * positions
        height = bone.support(axial, side, _ELEVATION_MARGIN_MM)
        across = np.einsum("ij,ij->i", bone.section_centre(axial), lateral) + offset
        x_axis = lateral
    y_axis = -u
    if flip:
        x_axis = -x_axis
    z_axis = np.cross(x_axis, y_axis)
    R_base = np.stack([x_axis, y_axis, z_axis], axis=-1)  # (N, 3, 3), columns
    face_centre = (bone.centre + axial[:, None] * e0 + (height + distance)[:, None] * u
                   + across[:, None] * lateral)
    R = R_base @ _rot_y(twist) @ _rot_x(tilt_x) @ _rot_z(tilt_y)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = face_centre - (probe.width_mm / 2) * R[:, :, 0]
    T[:, 3, 3] = 1.0
    return SweepTrajectory("longitudinal" if longitudinal else "transverse", T, dropped,
                           positions, multipliers, tilt_x, tilt_y, twist, side, distance, offset,
                           R_base)


def ray_grid(T_ct_image: np.ndarray, width_mm: float, n_rays: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins ``(N, n_rays, 3)`` on the transducer face (at image x = (j + 0.5) *
    width / n_rays, y = 0) and unit directions ``(N, n_rays, 3)`` (image +y) of N slices."""
    T = np.asarray(T_ct_image, dtype=np.float64)
    xs = (np.arange(n_rays) + 0.5) * (width_mm / n_rays)
    origins = T[:, None, :3, 3] + xs[None, :, None] * T[:, None, :3, 0]
    directions = np.broadcast_to(T[:, None, :3, 1], origins.shape)
    return origins, directions
