"""Priors of a registration: what an operating room knows before the search.

A :class:`Prior` holds a rough initial pose ``T_init`` (``T_ct_us``, mm, e.g. from a navigation
system or a previous registration: ``comreg register --init TRANSFORM``) with its tolerances
``max_deg`` / ``max_mm``, and landmark pairs (:class:`Landmark`: a point picked on the CT and the
same anatomical point picked in the US data, ``--landmarks CT_POINTS US_POINTS``), each with its
own tolerance (mm). All of them are in one patient space (``space``; :meth:`Prior.in_space`
converts; the registrar works in the CT's).

What it means (:meth:`Prior.allows`): a pose ``T`` is *within the prior* when

- its rotation differs from ``T_init``'s by at most ``max_deg`` (the angle of
  ``R @ R_init.T``), and it places the US points' centroid ``c`` within ``max_mm`` of where
  ``T_init`` places it (``|T c - T_init c|``); and
- it puts every US landmark within its tolerance of its CT landmark (``|T us - ct|``).

How the pose search uses it (:func:`comreg_core.registration.search.search.search_poses`):

1. **Starts.** With ``T_init`` they replace the global grid and the patch orientations:
   ``T_init`` turned about the US centroid it places by shells of angles up to ``max_deg``
   (:data:`STEP_DEG` apart, coarser beyond :data:`MAX_ROTATIONS` rotations), each shell about
   axes spread evenly over the sphere (:meth:`Prior.init_rotations`); each rotation then shifted
   by up to ``max_mm`` (:func:`~comreg_core.registration.search.prior_starts.shift_vectors`): slid along the CT's long axis in
   ``slide_step_mm`` steps (ICP cannot undo a slide along a shaft), combined with no move
   across it, the move onto it (as the global grid starts, inside the bone) or ``max_mm / 2``
   either way along either short axis. Defaults (30 deg, 30 mm): 63 rotations, about 2,500
   starts. Without ``T_init`` the usual rotations are kept, unslid. **Landmarks** move every
   rotation so that the US landmarks' centroid lands on the CT landmarks' (with two or more,
   first turned by the least rotation that points the line between the two farthest apart the
   same way in both), shifted as above by up to the largest landmark tolerance; 3+ landmarks
   not on a line add their least-squares pose (``landmarks``). The network's pose (else
   ``T_init``) comes first, unmoved.
2. **Choice.** The screening keeps the poses within the prior first; refined poses outside it
   are also pulled back onto its edge (:meth:`Prior.clamp`, ``+clamped``); only poses within
   it are polished, chosen or the runner-up
   (:func:`~comreg_core.registration.search.polish.choose_and_polish`'s ``within``).
3. **Record** (:mod:`comreg_core.registration.judgement.prior_reasons`): ``result.json``'s
   ``prior`` and the reasons it gives the verdict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.geometry.metrics import rotation_angles_deg
from comreg_core.registration.search.prior_starts import (least_rotation, rotation_shells,
                                                         shift_vectors, sphere_points)
from comreg_core.transforms import (apply_transform, as_points, check_rigid, check_space,
                                    matmul, rotate, space_change)

#: Tolerances when only an initial pose is given (``--init`` without ``--init-tolerance``).
DEFAULT_MAX_DEG = 30.0
DEFAULT_MAX_MM = 30.0
#: A landmark's tolerance (mm) when neither its description (``tol=5``) nor
#: ``--landmark-tolerance`` gives one.
DEFAULT_LANDMARK_TOLERANCE_MM = 10.0
#: Kinds of prior, from what knows least to what knows most (:func:`prior_kind`): a verdict
#: calibration is fitted for one (``comreg calibrate --prior``).
PRIOR_KINDS = ("none", "init", "landmark")
#: A generic axis (unit) turning the axis set of the second round's starts.
_TURN_AXIS = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)


@dataclass(frozen=True)
class Landmark:
    """One landmark pair: ``ct`` ``(3,)`` mm (CT frame) and ``us`` ``(3,)`` mm (US frame), the
    same anatomical point; a pose is allowed when it puts ``us`` within ``tolerance_mm`` of
    ``ct``."""

    label: str
    ct: np.ndarray
    us: np.ndarray
    tolerance_mm: float = DEFAULT_LANDMARK_TOLERANCE_MM

    def __post_init__(self) -> None:
        for name in ("ct", "us"):
            object.__setattr__(self, name, as_points(np.reshape(getattr(self, name), (1, 3)),
                                                     f"landmark '{self.label}'")[0])
        if not (self.tolerance_mm > 0 and math.isfinite(self.tolerance_mm)):
            raise ComRegError(f"The landmark '{self.label}' has tolerance {self.tolerance_mm:g}"
                              " mm.", "Give a tolerance above 0 mm.")

    def to_json(self) -> dict[str, Any]:
        return {"label": self.label, "ct_mm": self.ct.tolist(), "us_mm": self.us.tolist(),
                "tolerance_mm": float(self.tolerance_mm)}


@dataclass(frozen=True)
class Prior:
    """What is known before the search (module docstring).

    Attributes:
        T_init: ``(4, 4)`` mm, the initial pose ``T_ct_us`` in ``space``, or None (landmarks
            only).
        max_deg, max_mm: its tolerances: rotation (deg, in (0, 180]) and the US centroid's
            shift (mm, > 0).
        landmarks: :class:`Landmark` pairs (CT and US points in ``space``).
        space: "LPS" or "RAS", the patient space of all of the above.
        init_file: where ``T_init`` was read from (recorded in ``result.json``), or None.
    """

    T_init: np.ndarray | None = None
    max_deg: float = DEFAULT_MAX_DEG
    max_mm: float = DEFAULT_MAX_MM
    landmarks: tuple[Landmark, ...] = field(default=())
    space: str = "LPS"
    init_file: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "space", check_space(self.space))
        object.__setattr__(self, "landmarks", tuple(self.landmarks))
        if self.T_init is None and not self.landmarks:
            raise ComRegError("A prior needs an initial pose or at least one landmark pair.",
                              "Give --init TRANSFORM and/or --landmarks CT_POINTS US_POINTS.")
        if self.T_init is not None:
            object.__setattr__(self, "T_init", check_rigid(np.asarray(self.T_init, float)))
        if not 0 < self.max_deg <= 180:
            raise ComRegError(f"The initial pose's rotation tolerance is {self.max_deg:g} deg.",
                              "Give one above 0 and at most 180 deg.")
        if not (self.max_mm > 0 and math.isfinite(self.max_mm)):
            raise ComRegError(f"The initial pose's distance tolerance is {self.max_mm:g} mm.",
                              "Give one above 0 mm.")

    def in_space(self, space: str) -> Prior:
        """The same prior expressed in ``space``."""
        C = space_change(self.space, check_space(space))
        return replace(self, space=check_space(space),
                       T_init=None if self.T_init is None else C @ self.T_init @ C.T,
                       landmarks=tuple(replace(lm, ct=apply_transform(C, lm.ct[None])[0],
                                               us=apply_transform(C, lm.us[None])[0])
                                       for lm in self.landmarks))

    # -- what is within --------------------------------------------------------------------

    def errors(self, poses: np.ndarray, centroid: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For ``(B, 4, 4)`` poses: ``(B,)`` rotation from ``T_init`` (deg), ``(B,)`` shift of
        the US ``centroid`` ``(3,)`` from where ``T_init`` puts it (mm; both 0 without
        ``T_init``) and ``(B, L)`` landmark errors (mm)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        rotation, shift = np.zeros(len(poses)), np.zeros(len(poses))
        if self.T_init is not None:
            rotation = rotation_angles_deg(poses, self.T_init)
            placed = rotate(centroid[None], poses[:, :3, :3])[:, 0] + poses[:, :3, 3]
            shift = np.linalg.norm(placed - apply_transform(self.T_init, centroid[None])[0],
                                   axis=1)
        landmark = np.zeros((len(poses), len(self.landmarks)))
        for k, lm in enumerate(self.landmarks):
            landmark[:, k] = np.linalg.norm(rotate(lm.us[None], poses[:, :3, :3])[:, 0]
                                            + poses[:, :3, 3] - lm.ct,
                                            axis=1)
        return rotation, shift, landmark

    def allows(self, poses: np.ndarray, centroid: np.ndarray) -> np.ndarray:
        """``(B,)`` bool: which of the ``(B, 4, 4)`` poses are within the prior (module
        docstring) for the US ``centroid`` ``(3,)`` mm."""
        rotation, shift, landmark = self.errors(poses, centroid)
        ok = (rotation <= self.max_deg + 1e-9) & (shift <= self.max_mm + 1e-9)
        tolerances = np.array([lm.tolerance_mm for lm in self.landmarks])
        return ok & (landmark <= tolerances + 1e-9).all(axis=1)

    def clamp(self, poses: np.ndarray, centroid: np.ndarray) -> np.ndarray:
        """``(B, 4, 4)`` poses pulled back into ``T_init``'s tolerances: a rotation beyond
        ``max_deg`` turned back towards ``T_init``'s onto it (along the shortest path), a US
        centroid beyond ``max_mm`` moved back towards ``T_init``'s placement onto it. Without
        ``T_init``: shifted so that the landmarks' mean error vector vanishes."""
        from scipy.spatial.transform import Rotation

        out = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
        if self.T_init is None:
            for T in out:
                T[:3, 3] += np.mean([lm.ct - apply_transform(T, lm.us[None])[0]
                                     for lm in self.landmarks], axis=0)
            return out
        R0 = self.T_init[:3, :3]
        home = apply_transform(self.T_init, centroid[None])[0]
        for T in out:
            turn = Rotation.from_matrix(matmul(T[:3, :3], R0.T)).as_rotvec()
            angle = np.degrees(np.linalg.norm(turn))
            R = T[:3, :3]
            if angle > self.max_deg:
                R = matmul(Rotation.from_rotvec(turn * (0.999 * self.max_deg / angle))
                           .as_matrix(), R0)
            placed = rotate(centroid[None], T[:3, :3])[0] + T[:3, 3]
            offset = placed - home
            if np.linalg.norm(offset) > self.max_mm:
                placed = home + offset * (0.999 * self.max_mm / np.linalg.norm(offset))
            T[:3, :3] = R
            T[:3, 3] = placed - rotate(centroid[None], R)[0]
        return out

    # -- starts ------------------------------------------------------------------------------

    def init_rotations(self, centroid: np.ndarray, grid_offset: float = 0.0
                       ) -> dict[str, np.ndarray]:
        """``{name: T (4, 4)}``: ``T_init`` turned about the US ``centroid`` (placed by it) by
        shells of angles up to ``max_deg`` about axes spread over the sphere (module docstring;
        ``init+r10a3``: 10 deg about axis 3), ``T_init`` itself first. ``grid_offset`` 0.5: the
        shells halfway between and the axes turned: the second round's (without ``T_init``)."""
        from scipy.spatial.transform import Rotation

        shells, counts = rotation_shells(self.max_deg, grid_offset)
        home = apply_transform(self.T_init, centroid[None])[0]
        out = {} if grid_offset else {"init": self.T_init.copy()}
        for angle, count in zip(shells, counts):
            axes = sphere_points(count)
            if grid_offset:  # by half the axes' spacing on the sphere
                spacing = math.sqrt(4 * math.pi / count)
                axes = Rotation.from_rotvec(_TURN_AXIS * spacing * grid_offset).apply(axes)
            for k, axis in enumerate(axes):
                G = np.eye(4)
                G[:3, :3] = Rotation.from_rotvec(axis * math.radians(angle)).as_matrix()
                G[:3, 3] = home - rotate(home[None], G[:3, :3])[0]
                out[f"init+r{angle:.3g}a{k}"] = matmul(G, self.T_init)
        return out

    def starts(self, rotations: dict[str, np.ndarray], centroid: np.ndarray,
               centre: np.ndarray, axes: np.ndarray, slide_step_mm: float,
               grid_offset: float = 0.0) -> dict[str, np.ndarray]:
        """The starts built on ``rotations`` ``{name: T (4, 4)}`` (module docstring, step 1):
        each moved onto the landmarks (when there are any; ``+lm``), then shifted
        (:func:`shift_vectors`: the US ``centroid`` ``(3,)`` placed by it slid along the CT's
        long axis ``axes[:, 0]`` and moved across it, onto it (through the CT's ``centre``) or
        half the reach along ``axes[:, 1]``/``axes[:, 2]``) by up to ``max_mm`` (with
        landmarks: their largest tolerance). The landmarks' Kabsch pose first when there are
        3+ not on a line."""
        if self.landmarks:
            reach = max(lm.tolerance_mm for lm in self.landmarks)
            rotations = {f"{name}+lm": self.onto_landmarks(T) for name, T in rotations.items()}
        else:
            reach = self.max_mm
        out: dict[str, np.ndarray] = {}
        kabsch = self.kabsch_pose()
        if kabsch is not None and not grid_offset:
            out["landmarks"] = kabsch
        for name, T in rotations.items():
            placed = rotate(centroid[None], T[:3, :3])[0] + T[:3, 3]
            for label, shift in shift_vectors(placed, centre, axes, reach, slide_step_mm,
                                              grid_offset).items():
                S = T.copy()
                S[:3, 3] += shift
                out[name + label] = S
        return out

    def onto_landmarks(self, T: np.ndarray) -> np.ndarray:
        """``T`` turned (2+ landmarks: by the least rotation making the line between the two
        landmarks farthest apart on the CT point the same way) and moved so that the US
        landmarks' centroid lands on the CT landmarks'."""
        us = np.array([lm.us for lm in self.landmarks])
        ct = np.array([lm.ct for lm in self.landmarks])
        R = T[:3, :3]
        if len(ct) >= 2:
            i, j = np.unravel_index(np.argmax(np.linalg.norm(ct[:, None] - ct[None], axis=2)),
                                    (len(ct), len(ct)))
            a, b = rotate((us[j] - us[i])[None], R)[0], ct[j] - ct[i]
            if np.linalg.norm(a) > 1e-6 and np.linalg.norm(b) > 1e-6:
                R = matmul(least_rotation(a, b), R)
        out = np.eye(4)
        out[:3, :3] = R
        out[:3, 3] = ct.mean(axis=0) - rotate(us.mean(axis=0)[None], R)[0]
        return out

    def kabsch_pose(self) -> np.ndarray | None:
        """The least-squares rigid ``T`` of the landmark pairs (US -> CT), None with fewer than
        3 or when they lie on a line (less than 1 mm off it)."""
        if len(self.landmarks) < 3:
            return None
        us = np.array([lm.us for lm in self.landmarks])
        ct = np.array([lm.ct for lm in self.landmarks])
        centred = us - us.mean(axis=0)
        if np.linalg.svd(centred, compute_uv=False)[1] < 1.0:
            return None
        U, _, Vt = np.linalg.svd(centred.T @ (ct - ct.mean(axis=0)))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        T = np.eye(4)
        T[:3, :3] = Vt.T @ D @ U.T
        T[:3, 3] = ct.mean(axis=0) - T[:3, :3] @ us.mean(axis=0)
        return T


def prior_kind(prior: Prior | None) -> str:
    """The kind (:data:`PRIOR_KINDS`) of ``prior``: ``"landmark"`` with landmark pairs (with or
    without an initial pose), ``"init"`` with an initial pose only, ``"none"`` for None."""
    if prior is None:
        return "none"
    return "landmark" if prior.landmarks else "init"
