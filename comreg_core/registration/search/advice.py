"""What would resolve an ambiguous registration: where the competing pose puts the sweep.

When another, clearly different pose fits the US points nearly as well as the chosen one
(:attr:`SearchResult.ambiguous`), the geometry of this sweep cannot tell them apart; more
sweep can. :func:`ambiguity_advice` describes the runner-up against the chosen pose in the CT's
own terms (how far along the bone's long axis it puts the sweep, how far it turns it) and says
what to scan: along the bone towards the nearer end when the poses differ by a slide, another
face when they differ by a turn about the shaft, a longer stretch when one is flipped end to end.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from comreg_core.registration.geometry.extent import extent_bounds_mm
from comreg_core.registration.geometry.metrics import rotation_error_deg
from comreg_core.registration.geometry.surface import SurfaceCloud
from comreg_core.transforms import apply_transform, space_change

#: Poses turned apart by less than this (deg) differ by a slide along the bone.
SLIDE_ONLY_DEG = 30.0
#: Turned apart by more than this (deg): flipped end to end.
FLIPPED_DEG = 150.0


def end_names(axis: np.ndarray) -> tuple[str, str]:
    """Names of the bone's ends at ``+axis`` and ``-axis`` (unit, patient LPS mm): the
    anatomical direction the axis is closest to (LPS: +z superior, +x left, +y posterior)."""
    k = int(np.argmax(np.abs(axis)))
    names = (("left", "right"), ("posterior", "anterior"), ("superior", "inferior"))[k]
    return names if axis[k] > 0 else names[::-1]


def ambiguity_advice(T_chosen: np.ndarray, T_other: np.ndarray, us_centroid: np.ndarray,
                     target: SurfaceCloud, *, space: str = "LPS") -> dict[str, Any]:
    """Where ``T_other`` (the runner-up) puts the sweep compared with ``T_chosen`` (both
    ``(4, 4)`` ``T_ct_us`` mm), and what to scan to tell them apart.

    Args:
        us_centroid: ``(3,)`` mm, the US points' centroid (US frame).
        target: the CT cloud (its principal frame: centre, long axis).
        space: the CT's patient space ("LPS"/"RAS"), for the names of the bone's ends.

    Returns:
        ``{"slide_mm", "turn_deg", "lateral_mm", "at_percent_of_length", "other_at_percent",
        "advice"}``: the signed distance along the long axis from where the chosen pose puts the
        sweep to where the other does, their rotation apart, the distance across the axis, both
        positions along the bone (0 % at the ``-axis`` end), and one sentence for the user.
    """
    axis = target.axes[:, 0]
    along = (target.points - target.centre) @ axis
    lo, hi = float(along.min()), float(along.max())
    c1 = apply_transform(T_chosen, us_centroid[None])[0]
    c2 = apply_transform(T_other, us_centroid[None])[0]
    a1, a2 = float((c1 - target.centre) @ axis), float((c2 - target.centre) @ axis)
    across = (c2 - c1) - ((c2 - c1) @ axis) * axis
    turn = rotation_error_deg(T_chosen, T_other)
    lps_axis = axis * (np.array([-1.0, -1.0, 1.0]) if space == "RAS" else 1.0)
    plus_end, minus_end = end_names(lps_axis)
    nearer = plus_end if a1 > 0.5 * (lo + hi) else minus_end
    if turn < SLIDE_ONLY_DEG:
        advice = (f"The sweep fits about as well {abs(a2 - a1):.0f} mm further "
                  f"{'towards the ' + (plus_end if a2 > a1 else minus_end) + ' end'} along the "
                  f"bone: extend the sweep along the bone towards the {nearer} end until it "
                  "covers a distinctive part (an end, a ridge, a bump).")
    elif turn > FLIPPED_DEG:
        advice = (f"The sweep fits about as well flipped end to end ({turn:.0f} deg apart), "
                  f"{abs(a2 - a1):.0f} mm away along the bone: sweep a longer stretch, towards "
                  f"the {nearer} end.")
    else:
        advice = (f"The sweep fits about as well turned {turn:.0f} deg about the bone: sweep "
                  "over another face of the bone too (e.g. turn the probe around the limb).")
    length = max(hi - lo, 1e-9)
    return {"slide_mm": a2 - a1, "turn_deg": turn, "lateral_mm": float(np.linalg.norm(across)),
            "at_percent_of_length": 100.0 * (a1 - lo) / length,
            "other_at_percent": 100.0 * (a2 - lo) / length, "advice": advice}


#: An end of the bone counts as reached when the points come this close to it (mm).
END_REACHED_MM = 15.0


def scan_advice(points_ct: np.ndarray, target, space: str = "LPS") -> str:
    """Where to scan next: towards the end of the bone the registered points ``(N, 3)`` (CT
    frame, mm) lie nearer to, along the CT's long axis (``target``: its
    :class:`~comreg_core.registration.geometry.surface.SurfaceCloud`, centre and axes), or towards the
    other end when they already reach that one (within :data:`END_REACHED_MM`). The ends are
    named as anatomy names a limb's: the superior end proximal, the inferior end distal (other
    axes by their direction, e.g. "the left end")."""
    axis = target.axes[:, 0]
    along_ct = (target.points - target.centre) @ axis
    lo, hi = float(along_ct.min()), float(along_ct.max())
    along = (points_ct - target.centre) @ axis
    a, b = extent_bounds_mm(along)
    plus, minus = end_names(space_change(space, "LPS")[:3, :3] @ axis)
    towards_plus = 0.5 * (a + b) > 0.5 * (lo + hi)
    if towards_plus and hi - b < END_REACHED_MM:
        towards_plus = False
    elif not towards_plus and a - lo < END_REACHED_MM:
        towards_plus = True
    name = plus if towards_plus else minus
    limb = {"superior": "proximal", "inferior": "distal"}
    return f"scan towards the {limb.get(name, name)} end" + (
        f" ({name})" if name in limb else "")


def choice_evidence(poses: np.ndarray, scores: np.ndarray, best: int, runner: int | None,
                    config, centroid: np.ndarray, target: SurfaceCloud, space: str = "LPS"
                    ) -> tuple[float, bool, dict[str, Any] | None]:
    """``(confidence, ambiguous, advice)`` of choosing pose ``best`` over the ``runner`` up
    (indices into ``(B, 4, 4)`` poses and ``(B,)`` scores, mm; None: no distinct pose):
    :func:`~comreg_core.registration.search.scoring.confidence_over`, below the config's
    ``min_confidence``, and :func:`ambiguity_advice` when ambiguous."""
    from comreg_core.registration.search.scoring import confidence_over

    confidence = 1.0 if runner is None else float(
        confidence_over(scores[best], scores[runner], config))
    ambiguous = confidence < config.min_confidence
    advice = None
    if ambiguous and runner is not None:
        advice = ambiguity_advice(poses[best], poses[runner], centroid, target, space=space)
    return confidence, ambiguous, advice
