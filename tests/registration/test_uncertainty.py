"""The pose's uncertainty (registration/judgement/uncertainty.py and friends) against Monte-Carlo
fits with per-frame noise, a planted second basin and a knob to scan.

Shapes are tubes ``r(theta, z) = R + bumps`` meshed finely (closest points to the triangles,
the same CTSurface the product uses); sweeps are frames across the tube (a frame: the points of
one z on the side facing +y). Per-frame noise: each frame is shifted in its plane (0.3 mm per
axis) and turned about the tube's axis by 0.3 deg; every point gets 0.1 mm along its normal.
The Monte-Carlo reference fits each noisy sweep by Gauss-Newton point-to-plane steps solved by
``numpy.linalg.lstsq`` (the minimum-norm step leaves unconstrained directions where they are).
"""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.registration.judgement.assessment import pose_uncertainty
from comreg_core.registration.judgement.uncertainty import fit_moments, target_error

RADIUS = 10.0
LENGTH = 300.0


def tube(bumps=(), n_theta=240, dz=0.5):
    """A CTSurface of a tube along z, radius :data:`RADIUS`, with Gaussian ``bumps`` ``(theta0
    rad, z0 mm, height mm, width mm)``."""
    theta = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    z = np.arange(-LENGTH / 2, LENGTH / 2 + dz / 2, dz)
    tt, zz = np.meshgrid(theta, z, indexing="ij")
    r = np.full_like(tt, RADIUS)
    for t0, z0, h, w in bumps:
        arc = RADIUS * np.angle(np.exp(1j * (tt - t0)))
        r += h * np.exp(-((zz - z0) ** 2 + arc ** 2) / (2 * w ** 2))
    vertices = np.stack([r * np.cos(tt), r * np.sin(tt), zz], axis=-1).reshape(-1, 3)
    nt, nz = tt.shape
    idx = np.arange(nt * nz).reshape(nt, nz)
    a, b = idx[:, :-1], idx[:, 1:]
    c, d = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])
    return CTSurface((vertices, faces))


def sweep_frames(surface, z_values, arc_deg=140.0, per_frame=30):
    """``(points (n, 3), frame (n,))`` on the surface: per frame z, ``per_frame`` points on the
    arc facing +y (closest surface points to rays of the ideal circle)."""
    theta = np.radians(90.0 + np.linspace(-arc_deg / 2, arc_deg / 2, per_frame))
    points, frames = [], []
    for k, z in enumerate(z_values):
        ring = np.stack([2 * RADIUS * np.cos(theta), 2 * RADIUS * np.sin(theta),
                         np.full(per_frame, z)], -1)
        # walk inwards to the surface: the closest surface point of a point just outside
        closest, _, _ = surface.closest(ring * [0.55, 0.55, 1.0])
        points.append(closest)
        frames.append(np.full(per_frame, k))
    return np.concatenate(points), np.concatenate(frames)


def noisy(points, frames, normals, rng):
    out = points.copy()
    for k in np.unique(frames):
        m = frames == k
        angle = np.radians(rng.normal(0, 0.3))
        c, s = np.cos(angle), np.sin(angle)
        xy = out[m, :2] @ np.array([[c, -s], [s, c]]).T
        out[m, :2] = xy + rng.normal(0, 0.3, 2)
    return out + normals * rng.normal(0, 0.1, (len(out), 1))


def gauss_newton(points, surface, iterations=6):
    """The pose (rotation vector rad (3,), translation mm (3,)) about the origin that fits the
    points to the surface: numpy lstsq steps (minimum norm)."""
    from scipy.spatial.transform import Rotation

    R, t = np.eye(3), np.zeros(3)
    for _ in range(iterations):
        moved = points @ R.T + t
        q, n, d = surface.closest(moved, 10.0)
        ok = np.isfinite(d)
        J = np.hstack([np.cross(moved[ok], n[ok]), n[ok]])
        r = np.sum((moved[ok] - q[ok]) * n[ok], axis=1)
        step = np.linalg.lstsq(J, -r, rcond=1e-10)[0]
        dR = Rotation.from_rotvec(step[:3]).as_matrix()
        R, t = dR @ R, dR @ t + step[3:]
    return Rotation.from_matrix(R).as_rotvec(), t


@pytest.fixture(scope="module")
def cylinder():
    return tube()


@pytest.fixture(scope="module")
def knobbly():
    """A tube with three bumps around a 40 mm stretch: every direction is pinned."""
    return tube(bumps=[(np.radians(60), -12.0, 3.0, 4.0), (np.radians(120), 10.0, 3.0, 4.0),
                       (np.radians(90), 0.0, -2.0, 5.0)])


def monte_carlo(surface, z_values, fits=200, seed=0):
    clean, frames = sweep_frames(surface, z_values)
    _, normals, _ = surface.closest(clean)
    rng = np.random.default_rng(seed)
    poses = np.array([np.concatenate(gauss_newton(noisy(clean, frames, normals, rng), surface))
                      for _ in range(fits)])
    return clean, frames, normals, poses


def origin_covariance(fit):
    """``(3, 3)`` covariance of the translation at the origin (the poses' own parameters):
    ``t0 = t_centre + centre x w``."""
    c = fit.centre
    cross = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
    L = np.hstack([cross / fit.scale, np.eye(3)])
    return L @ fit.covariance @ L.T


def predicted(surface, clean, frames, normals, seed=1, draws=5):
    """The uncertainty of ``draws`` noisy sweeps (each registered at the truth, the identity)."""
    rng = np.random.default_rng(seed)
    return [fit_moments(noisy(clean, frames, normals, rng), np.eye(4), surface,
                        free_mm=LENGTH) for _ in range(draws)]


def test_cylinder_bounds_match_monte_carlo_and_the_axis_is_unbounded(cylinder):
    clean, frames, normals, poses = monte_carlo(cylinder, np.arange(-20.0, 20.5, 1.0))
    fits = predicted(cylinder, clean, frames, normals)
    # across the tube (x, y translation of its axis, at the origin) and its tilts (rx): the
    # sandwich against the Monte-Carlo spread of the fitted poses
    for axis in (0, 1):
        sd_mc = float(np.std(poses[:, 3 + axis]))
        sd = np.median([np.sqrt(origin_covariance(f)[axis, axis]) for f in fits])
        assert sd == pytest.approx(sd_mc, rel=0.3), (axis, sd, sd_mc)
    sd_tilt_mc = float(np.std(poses[:, 0]))
    sd_tilt = np.median([np.sqrt(f.covariance[0, 0]) / f.scale for f in fits])
    assert sd_tilt == pytest.approx(sd_tilt_mc, rel=0.3)
    # along the axis and about it nothing is pinned: unbounded, not a small number
    u = pose_uncertainty(noisy(clean, frames, normals, np.random.default_rng(5)), np.eye(4),
                         cylinder, ct_length_mm=LENGTH, profiles=False, advice=False)
    slide, roll = u.directions
    assert slide["unbounded"] and slide["bound_mm"] > 100 and "along" in slide["words"]
    assert roll["unbounded"] and roll["bound_deg"] > 45 and "about" in roll["words"]
    assert u.p_local < 0.2


def test_featured_shape_bound_matches_monte_carlo(knobbly):
    clean, frames, normals, poses = monte_carlo(knobbly, np.arange(-20.0, 20.5, 1.0))
    targets = clean[::10]
    from scipy.spatial.transform import Rotation

    moved = np.stack([targets @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:] - targets
                      for p in poses])
    mc_bound = float(np.percentile(np.linalg.norm(moved, axis=2).max(axis=1), 95))
    bounds = [target_error(f, f.covariance)[0] for f in predicted(knobbly, clean, frames,
                                                                  normals)]
    assert np.median(bounds) == pytest.approx(mc_bound, rel=0.3), (bounds, mc_bound)
    assert 0.2 < mc_bound < 4.0  # a real spread, well inside the tolerance


def test_profile_finds_a_planted_second_basin():
    # two identical knobs 36 mm apart: a sweep over one fits the other as well
    twin = tube(bumps=[(np.radians(90), 0.0, 3.0, 4.0), (np.radians(90), 36.0, 3.0, 4.0)])
    single = tube(bumps=[(np.radians(90), 0.0, 3.0, 4.0)])
    points, frames = sweep_frames(twin, np.arange(-8.0, 8.5, 1.0))
    rng = np.random.default_rng(3)
    _, normals, _ = twin.closest(points)
    points = noisy(points, frames, normals, rng)
    twins = pose_uncertainty(points, np.eye(4), twin, ct_length_mm=LENGTH, advice=False)
    alone = pose_uncertainty(points, np.eye(4), single, ct_length_mm=LENGTH, advice=False)
    slide = next(p for p in twins.profiles if p["kind"] == "slide")
    found = [r for r in slide["offsets"] if r["different"] and r["weight"] > 0.1]
    assert found and all(r["offset"] > 0 for r in found)  # towards the twin knob only
    assert twins.p_basin < 0.9 and alone.p_basin > 0.99
    assert twins.p_raw < alone.p_raw


def test_advice_on_a_cylinder_points_at_the_knob():
    knob_z = 60.0
    surface = tube(bumps=[(np.radians(90), knob_z, 3.0, 4.0)])
    points, frames = sweep_frames(surface, np.arange(-20.0, 20.5, 1.0))
    _, normals, _ = surface.closest(points)
    points = noisy(points, frames, normals, np.random.default_rng(4))
    u = pose_uncertainty(points, np.eye(4), surface, ct_length_mm=LENGTH, profiles=False)
    advice = u.scan_next
    knob = np.array([0.0, RADIUS + 3.0, knob_z])
    assert np.linalg.norm(np.array(advice["point_ct"]) - knob) < 15.0, advice
    assert advice["bound_mm"] < 0.5 * u.bound_mm
    assert "superior end" in advice["words"] and "pointing posterior" in advice["words"]  # LPS +z, +y


def test_advice_ranks_the_patches_as_one_at_a_time():
    """The patches ranked in one compiled pass give, bit for bit, what scanning each patch in
    turn gives (its information added to the fit's, the 95 % bound of 256 draws)."""
    from comreg_core.registration.judgement import scan_next as sn
    from comreg_core.registration.judgement import uncertainty_kernels as kern
    from comreg_core.registration.judgement.uncertainty import BLOCK_MM, long_axis_of

    surface = tube(bumps=[(np.radians(90), 60.0, 3.0, 4.0)])
    points, frames = sweep_frames(surface, np.arange(-20.0, 20.5, 1.0))
    _, normals, _ = surface.closest(points)
    points = noisy(points, frames, normals, np.random.default_rng(5))
    fit = fit_moments(points, np.eye(4), surface, free_mm=LENGTH)
    advice = sn.scan_next(fit, fit.covariance, surface, long_axis_of(surface), 2.0)

    samples, sample_normals = surface.samples(sn.SCAN_SAMPLES)
    group, count = sn.block_groups(samples, sn.PATCH_MM)
    weight = float(surface.face_areas.sum()) / sn.SCAN_SAMPLES * (
        fit.inliers / (fit.blocks * BLOCK_MM ** 2))
    now, _ = target_error(fit, fit.c * kern.inverse(fit.A), sn.RANK_SAMPLES)
    best, ranked = None, 0
    for k in range(count):
        member = group == k
        mean = sample_normals[member].mean(axis=0)
        if member.sum() < sn.MIN_PATCH_SAMPLES or mean @ fit.normal_mean <= 0:
            continue  # too small, or on the far side of the bone
        H, _, _ = kern.moments(samples[member], samples[member], sample_normals[member],
                               fit.centre, fit.scale, np.zeros(member.sum(), dtype=np.int64), 1)
        bound, _ = target_error(fit, fit.c * kern.inverse(fit.A + weight * H), sn.RANK_SAMPLES)
        ranked += 1
        if best is None or bound < best[0]:
            best = (bound, samples[member].mean(axis=0))
    assert ranked > 10
    assert advice["point_ct"] == [float(x) for x in best[1]]
    assert advice["bound_mm"] == 2.0 * best[0] / now


def slid_along_axis(mm):
    T = np.eye(4)
    T[2, 3] = mm
    return T


def test_the_search_s_competitor_is_weighed_by_the_basin_it_falls_in():
    twin = tube(bumps=[(np.radians(90), 0.0, 3.0, 4.0), (np.radians(90), 36.0, 3.0, 4.0)])
    single = tube(bumps=[(np.radians(90), 0.0, 3.0, 4.0)])
    points, frames = sweep_frames(twin, np.arange(-8.0, 8.5, 1.0))
    _, normals, _ = twin.closest(points)
    points = noisy(points, frames, normals, np.random.default_rng(3))

    def weighed(surface, mm):
        return pose_uncertainty(points, np.eye(4), surface, ct_length_mm=LENGTH, advice=False,
                                profiles=False, competitors=[slid_along_axis(mm)])

    # 33 mm along, short of the twin knob: refitted it lands on the twin, as good a fit
    twins = weighed(twin, 33.0)
    assert not twins.competitor["same_basin"] and twins.competitor["delta_cost"] < 1.0
    assert twins.competitor["weight"] > 0.6 and twins.p_basin < 0.65
    # on the tube with one knob the same pose fits clearly worse (chi-square > 10)
    alone = weighed(single, 33.0)
    assert alone.competitor["delta_cost"] > 10.0 and alone.p_basin > 0.99
    # 4.5 mm off, a pose the search left unfinished: refitted it falls into the chosen basin
    unfinished = weighed(single, 4.5)
    assert unfinished.competitor["same_basin"] and unfinished.competitor["weight"] == 0.0
    assert unfinished.p_basin == 1.0
    # 2 mm off: the same answer at this fit's targets whatever the search called it; recorded
    # as such (weight 0), so that the search's ambiguity about it can be overruled
    close = weighed(single, 2.0)
    assert close.competitor["same_basin"] and close.competitor["weight"] == 0.0


def test_basins_are_weighed_bottom_against_bottom():
    """The chosen pose as given may sit off the judge's own optimum (the search polishes by
    another measure): other basins are weighed against its refit, not against it."""
    from comreg_core.registration.judgement.profile import ChosenBasin
    from comreg_core.registration.judgement.uncertainty import truncated_cost

    twin = tube(bumps=[(np.radians(90), 0.0, 3.0, 4.0), (np.radians(90), 36.0, 3.0, 4.0)])
    points, frames = sweep_frames(twin, np.arange(-8.0, 8.5, 1.0))
    _, normals, _ = twin.closest(points)
    points = noisy(points, frames, normals, np.random.default_rng(3))
    off = slid_along_axis(1.5)  # unfinished, within the tolerance
    fit = fit_moments(points, off, twin, free_mm=LENGTH)
    base = ChosenBasin.of(points, off, twin, fit).cost
    as_given = truncated_cost(points, off, twin, fit)
    assert base < as_given - 5.0  # 1.5 mm off a knob costs clearly more than its bottom
    # the same bottom as from the pose at the knob
    assert base == pytest.approx(ChosenBasin.of(points, np.eye(4), twin, fit).cost, abs=0.5)
    # the twin knob 36 mm along weighs what it weighs against the pose at the optimum
    at_optimum = pose_uncertainty(points, np.eye(4), twin, ct_length_mm=LENGTH, advice=False,
                                  profiles=False, competitors=[slid_along_axis(33.0)])
    unfinished = pose_uncertainty(points, off, twin, ct_length_mm=LENGTH, advice=False,
                                  profiles=False, competitors=[slid_along_axis(33.0)])
    assert unfinished.competitor["delta_cost"] == pytest.approx(
        at_optimum.competitor["delta_cost"], abs=1.0)  # against the pose as given: 5+ less


def test_neighbour_probe_finds_a_basin_just_beyond_the_tolerance():
    """Two narrow knobs 7 mm apart and a sweep over one: the pose on the other is a different
    answer (7 mm > 4 mm) that fits as well; the profiles' 15-35 mm offsets step over it."""
    from comreg_core.registration.judgement.profile import weigh_basins

    knob = (np.radians(90), 0.0, 2.0, 1.5)
    twin = tube(bumps=[knob, (np.radians(90), 7.0, 2.0, 1.5)], dz=0.25)
    single = tube(bumps=[knob], dz=0.25)
    points, frames = sweep_frames(twin, np.arange(-3.0, 3.25, 0.5))
    _, normals, _ = twin.closest(points)
    points = noisy(points, frames, normals, np.random.default_rng(6))
    found = {}
    for name, surface in (("twin", twin), ("single", single)):
        fit = fit_moments(points, np.eye(4), surface, free_mm=LENGTH)
        found[name] = weigh_basins(points, np.eye(4), surface, fit, neighbours=True).neighbours
    assert max(n["weight"] for n in found["twin"]) > 0.3, found["twin"]
    assert max([n["weight"] for n in found["single"]], default=0.0) < 1e-3, found["single"]
    # and it lowers the pose's p_basin where the profiles alone do not
    u = pose_uncertainty(points, np.eye(4), twin, ct_length_mm=LENGTH, advice=False)
    assert u.neighbours and u.p_basin < 0.8
