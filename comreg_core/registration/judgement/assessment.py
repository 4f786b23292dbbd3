"""The pose's uncertainty of one registration, all parts together (:func:`pose_uncertainty`):
the local bound, the weakest directions, the profiles, the competitor, and where to scan next.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from comreg_core.registration.judgement.profile import weigh_basins
from comreg_core.registration.judgement.scan_next import scan_next
from comreg_core.registration.judgement.uncertainty import (extent_along, fit_moments,
                                                            long_axis_of, target_error,
                                                            weakest_directions)


@dataclass(frozen=True)
class Uncertainty:
    """How far off a pose can be (:mod:`.uncertainty`).

    Attributes:
        bound_mm: 95 % bound of the largest target error over the CT surface under the sweep.
        p_local, p_basin: the share of local pose errors within 4 mm / 5 deg, and the chosen
            basin's weight against the profiled and competing ones; ``p_raw`` their product.
        directions: the weakest slide and rotation (:func:`.uncertainty.weakest_directions`,
            widened to the profile's flat stretch).
        noise_mm, design_effect, groups: the fit's robust noise per point, its design effect
            and the number of independent groups of points.
        profiles, competitor, neighbours: :func:`.profile.weigh_basins`' profiles of both
            directions, the search's clinically different pose's excess cost and weight (or
            None) and the neighbour probe's basins.
        scan_next: :func:`.scan_next.scan_next` (or None).
    """

    bound_mm: float
    p_local: float
    p_basin: float
    directions: list[dict[str, Any]]
    noise_mm: float
    design_effect: float
    groups: int
    profiles: list[dict[str, Any]] = field(default_factory=list)
    competitor: dict[str, Any] | None = None
    neighbours: list[dict[str, Any]] = field(default_factory=list)
    scan_next: dict[str, Any] | None = None

    @property
    def p_raw(self) -> float:
        return self.p_local * self.p_basin

    def weakest_words(self) -> str:
        """``"along the bone's long axis 2.1 mm, about the bone's long axis 1.4 deg"``."""
        parts = []
        for d in self.directions:
            value = (f"{d['bound_mm']:.1f} mm" if d["kind"] == "slide"
                     else f"{d['bound_deg']:.1f} deg")
            parts.append(f"{d['words']} {'unbounded' if d['unbounded'] else value}")
        return ", ".join(parts)

    def summary(self) -> str:
        """One line: the bound and the weakest directions."""
        return (f"within {self.bound_mm:.1f} mm (95 %); weakest: {self.weakest_words()}")

    def to_json(self) -> dict[str, Any]:
        """``result.json``'s ``uncertainty``."""
        return {"bound_mm": self.bound_mm, "p_local": self.p_local, "p_basin": self.p_basin,
                "p_raw": self.p_raw, "directions": self.directions,
                "noise_mm": self.noise_mm, "design_effect": self.design_effect,
                "groups": self.groups, "profiles": self.profiles,
                "competitor": self.competitor, "neighbours": self.neighbours,
                "summary": self.summary()}


def pose_uncertainty(points_us: np.ndarray, T_ct_us: np.ndarray, surface, *,
                     ct_length_mm: float | None = None, prior_mm: float | None = None,
                     prior_deg: float | None = None,
                     competitors: Sequence[np.ndarray] = (),
                     groups: np.ndarray | None = None, profiles: bool = True,
                     advice: bool = True) -> Uncertainty | None:
    """The :class:`Uncertainty` of ``T_ct_us`` (``(4, 4)`` mm) for ``(n, 3)`` US points on the
    CT ``surface`` (a CTSurface) ``ct_length_mm`` long (None: its vertices' spread along their
    long axis). ``prior_mm``/``prior_deg``: the
    prior's tolerances; ``competitors``: clinically different poses ``(4, 4)`` the search
    found (the first is weighed); ``groups``: ``(n,)`` frame of each point (None: blocks);
    ``profiles``/``advice``: whether to profile the weakest directions (and probe the
    neighbouring basins) and to find where to scan next. None when too few points meet the
    CT."""
    long_axis = long_axis_of(surface)
    if ct_length_mm is None:
        low, high = extent_along(surface.vertices, long_axis)
        ct_length_mm = high - low
    fit = fit_moments(points_us, T_ct_us, surface, free_mm=ct_length_mm, prior_mm=prior_mm,
                      prior_deg=prior_deg, groups=groups)
    if fit is None:
        return None
    covariance = fit.covariance
    directions = weakest_directions(fit, covariance, long_axis)
    competitor = np.asarray(competitors[0], dtype=np.float64) if len(competitors) else None
    basins = weigh_basins(points_us, T_ct_us, surface, fit,
                          directions=[(d["kind"], np.asarray(d["axis_ct"])) for d in directions]
                          if profiles else (),
                          neighbours=profiles, competitor=competitor,
                          costed=bool(profiles or competitor is not None))
    bound, p_local = target_error(fit, covariance, offset=basins.chosen.offset(fit))
    weights = []
    for d, run in zip(directions, basins.profiles):
        for sign in (1.0, -1.0):
            side = [r["weight"] for r in run["offsets"] if r["offset"] * sign > 0]
            weights.append(max(side, default=0.0))
        key = "bound_mm" if d["kind"] == "slide" else "bound_deg"
        d[key] = max(d[key], run["flat_to"])
    bound = max([bound] + [r["flat_to"] for r in basins.profiles if r["kind"] == "slide"])
    weights += [n["weight"] for n in basins.neighbours]
    if basins.competitor is not None:
        weights.append(basins.competitor["weight"])
    p_basin = 1.0 / (1.0 + float(sum(weights)))
    advice_record = scan_next(fit, covariance, surface, long_axis, bound) if advice else None
    return Uncertainty(bound_mm=float(bound), p_local=p_local, p_basin=p_basin,
                       directions=directions, noise_mm=fit.noise_mm,
                       design_effect=fit.design_effect, groups=fit.groups,
                       profiles=basins.profiles, competitor=basins.competitor,
                       neighbours=basins.neighbours,
                       scan_next=advice_record)

