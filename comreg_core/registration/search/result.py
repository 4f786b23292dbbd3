"""The result of registering one US cloud, whichever way it was made, and its residuals."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from comreg_core.registration.search.scoring import SearchResult

#: Registered points within this distance (mm) of the CT surface count as inliers.
INLIER_MM = 2.0


@dataclass
class RegistrationResult:
    """The registration of one US cloud (mm, CT frame = the CT mesh's space).

    Attributes:
        T_ct_us: ``(4, 4)`` final estimate (after ICP): ``T_ct_us @ p_us = p_ct``.
        T_ct_us_coarse: ``(4, 4)`` the pose head's estimate before ICP.
        registered_points: ``(N, 3)`` the US points mapped by ``T_ct_us``.
        completion_ct: ``(M, 3)`` the completed bone (network output in the US frame) mapped by
            ``T_ct_us`` into the CT frame.
        timings: seconds per stage (:mod:`comreg_core.register`).
        runtime_s: registration time (= ``timings["total"]``).
        device: torch device used.
        seed: the seed given to :meth:`comreg_core.register.Registrar.register` (torch's
            generator is seeded with it; the eval-mode forward pass is deterministic anyway).
        residuals: distances (mm) of ``registered_points`` to the CT surface: ``mean``,
            ``median``, ``p90``, ``p95``, ``max``, ``rmse``, and ``inlier_fraction`` (share
            within :data:`INLIER_MM`).
        icp_rmse: the final RMS residual (mm) of the ICP that produced ``T_ct_us``: the
            network's (weighted, normalised units x CT scale), or with the pose search the
            polish's RMS distance of the matched points to the mesh (the chosen candidate's
            point-to-plane residual when there was no polish).
        n_points: points in the US cloud.
        search: the pose search's :class:`~comreg_core.registration.SearchResult` (chosen
            candidate, every score, runner-up, gap, confidence, ambiguous), None when it was
            off.
        info: JSON-able extras (what the evaluation harness records per trial): the coarse
            pose, timings, residuals, ``search`` (the block of :meth:`to_json`, None when
            off) and, when the search ran, ``ambiguous`` and ``confidence``.

    ``confidence`` and ``ambiguous`` (properties) are those of ``search``, None when off.
    """

    T_ct_us: np.ndarray
    T_ct_us_coarse: np.ndarray
    registered_points: np.ndarray
    completion_ct: np.ndarray
    timings: dict[str, float]
    runtime_s: float
    device: str
    seed: int
    residuals: dict[str, float]
    icp_rmse: float
    n_points: int
    search: SearchResult | None = None
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def confidence(self) -> float | None:
        """:attr:`SearchResult.confidence` in [0, 1]; None without the pose search."""
        return None if self.search is None else self.search.confidence

    @property
    def ambiguous(self) -> bool | None:
        """:attr:`SearchResult.ambiguous`; None without the pose search."""
        return None if self.search is None else self.search.ambiguous

    def to_json(self) -> dict[str, Any]:
        """The ``result.json`` content (without file names). ``confidence`` and ``ambiguous``
        are at the top level (null when the pose search was off); ``search`` holds the details
        (null when off): ``chosen``, ``runner_up``, ``score_mm``, ``score_gap_mm``,
        ``confidence``, ``ambiguous``, ``scores_mm`` (every candidate)."""
        return {
            "T_ct_us": self.T_ct_us.tolist(), "T_ct_us_coarse": self.T_ct_us_coarse.tolist(),
            "timings_s": self.timings, "runtime_s": self.runtime_s, "device": self.device,
            "seed": self.seed, "n_points": self.n_points, "residuals_mm": self.residuals,
            "icp_rmse_mm": self.icp_rmse, "confidence": self.confidence,
            "ambiguous": self.ambiguous,
            "search": None if self.search is None else self.search.to_json(),
            "warnings": list(self.info.get("warnings", [])),
        }


def residual_statistics(distances: np.ndarray) -> dict[str, float]:
    """``mean``, ``median``, ``p90``, ``p95``, ``max``, ``rmse`` (mm) and ``inlier_fraction``
    (share within :data:`INLIER_MM`) of registered points' ``(N,)`` distances to the CT."""
    d = np.asarray(distances, dtype=np.float64)
    return {"mean": float(d.mean()), "median": float(np.median(d)),
            "p90": float(np.percentile(d, 90)), "p95": float(np.percentile(d, 95)),
            "max": float(d.max()), "rmse": float(np.sqrt(np.mean(d ** 2))),
            "inlier_fraction": float(np.mean(d <= INLIER_MM))}
