"""Validation of a network during pretraining: its errors on the run's fixed held-out samples.

:func:`validate` registers the validation samples with the network in eval mode (CT half
encoded once; the ICP's pose refined on the CT mesh with ``model.icp.mesh_refine``) and
returns the ``val_*`` figures of ``training_log.csv``: RTE (mm, at the centroid of the moved
US cloud) and RRE (deg) as in :mod:`comreg_core.registration.geometry.metrics`, of
the fine (after ICP) and the coarse estimate; success = RTE < 2 mm and RRE < 2 deg, flip = RRE >
90 deg; the share of samples whose coarse RRE is under :data:`IMPROVED_RRE_FACTOR` of their
initial RRE (steadier than the coarse median, which jumps between the two groups of a bimodal
error: sweeps the network turns right and sweeps it leaves where they lie); the training
objective; and the evaluation's completion CD (mm) against the CT surface.
:func:`identity_errors` gives the same errors for doing nothing (the initial misalignment).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from comreg_core.model.comreg import ComRegNet
from comreg_core.model.losses import output_loss
from comreg_core.normalization import Normalization
from comreg_core.registration.geometry.icp import refine_on_mesh
from comreg_core.registration.geometry.metrics import (FLIP_RRE_DEG, completion_metrics,
                                                       is_success, rotation_error_deg,
                                                       translation_error_mm)
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.training.data import Sample
from comreg_core.transforms import invert_rigid, orthonormalize

#: A validation sample counts as improved when the coarse RRE is under this share of its
#: initial RRE (``val_coarse_improved_share``).
IMPROVED_RRE_FACTOR = 0.5


def _pose_errors(T_est_n: np.ndarray, sample: Sample, norm: Normalization) -> tuple[float, float]:
    T_est = norm.transform_to_mm(orthonormalize(T_est_n))
    truth = invert_rigid(sample.T_us_ct_mm)
    at = norm.points_to_mm(sample.source).mean(axis=0)
    return translation_error_mm(T_est, truth, at), rotation_error_deg(T_est, truth)


def _initial_errors(samples: list[Sample], norm: Normalization) -> np.ndarray:
    """``(n, 2)`` RTE (mm) and RRE (deg) of doing nothing, per sample."""
    return np.array([_pose_errors(np.eye(4), s, norm) for s in samples])


def validate(model: ComRegNet, ct_points_n: torch.Tensor, samples: list[Sample],
             norm: Normalization, batch_size: int = 8, loss=None,
             surface: CTSurface | None = None) -> dict[str, float]:
    """Register the validation samples; the ``val_*`` figures of
    :data:`~comreg_core.training.bookkeeping.LOG_COLUMNS` (``val_loss`` / ``val_completion``: the
    training objective and its completion term, means over the samples, in eval mode;
    ``val_completion_CD_mm_median``: the evaluation's completion CD
    (:func:`~comreg_core.registration.geometry.metrics.completion_metrics`) against ``surface``,
    the CT, when given)."""
    was_training = model.training
    model.eval()
    fine, coarse, completion_cd = [], [], []
    loss_sum = completion_sum = 0.0
    start = time.perf_counter()
    device = ct_points_n.device
    try:
        with torch.no_grad():
            encoding = model.encode_target(ct_points_n[None])
            for i in range(0, len(samples), batch_size):
                chunk = samples[i:i + batch_size]
                src = torch.from_numpy(np.stack([s.source for s in chunk])).float().to(device)
                out = model(src, encoding)
                gt_points = torch.from_numpy(np.stack([s.gt_points for s in chunk])).float()
                gt_transform = torch.from_numpy(np.stack([s.gt_transform for s in chunk])).float()
                terms = output_loss(out, gt_points.to(device), gt_transform.to(device), loss)
                loss_sum += float(terms.total) * len(chunk)
                completion_sum += float(terms.completion) * len(chunk)
                fine += list(out.fine_transform.double().cpu().numpy())
                coarse += list(out.coarse_transform.double().cpu().numpy())
                if surface is not None:
                    for dense, s in zip(out.completion.dense.double().cpu().numpy(), chunk):
                        completion_cd.append(completion_metrics(
                            norm.points_to_mm(dense), invert_rigid(s.T_us_ct_mm), surface,
                            n_ct_samples=4096)["completion_CD_mm"])
    finally:
        model.train(was_training)
    if model.config.icp.mesh_refine:  # as outside training: the ICP's pose refined on the mesh
        fine = _refined_on_mesh(fine, samples, norm, surface)
    fe = np.array([_pose_errors(T, s, norm) for T, s in zip(fine, samples)])
    ce = np.array([_pose_errors(T, s, norm) for T, s in zip(coarse, samples)])
    initial = _initial_errors(samples, norm)
    return {
        "val_RTE_mm_median": float(np.median(fe[:, 0])),
        "val_RRE_deg_median": float(np.median(fe[:, 1])),
        "val_RTE_mm_mean": float(fe[:, 0].mean()),
        "val_RRE_deg_mean": float(fe[:, 1].mean()),
        "val_coarse_RTE_mm_median": float(np.median(ce[:, 0])),
        "val_coarse_RRE_deg_median": float(np.median(ce[:, 1])),
        "val_coarse_improved_share": float(np.mean(ce[:, 1] < IMPROVED_RRE_FACTOR * initial[:, 1])),
        "val_success_rate": float(np.mean([is_success(t, r) for t, r in fe])),
        "val_flip_rate": float(np.mean(fe[:, 1] > FLIP_RRE_DEG)),
        "val_loss": loss_sum / len(samples),
        "val_completion": completion_sum / len(samples),
        "val_completion_CD_mm_median": (float(np.median(completion_cd)) if completion_cd
                                        else float("nan")),
        "val_s": time.perf_counter() - start,
    }


def _refined_on_mesh(poses: list[np.ndarray], samples: list[Sample], norm: Normalization,
                     surface: CTSurface | None) -> list[np.ndarray]:
    """The ``(4, 4)`` normalised poses refined on the CT mesh (``model.icp.mesh_refine``)."""
    if surface is None:
        raise ValueError("icp.mesh_refine needs the CT surface")
    match = surface.matcher()
    return [norm.transform_to_model(refine_on_mesh(
        norm.points_to_mm(s.source), norm.transform_to_mm(orthonormalize(T)), match)[0])
        for T, s in zip(poses, samples)]


def identity_errors(samples: list[Sample], norm: Normalization) -> dict[str, float]:
    """Validation errors of doing nothing (the initial misalignment): medians and means."""
    e = _initial_errors(samples, norm)
    return {"RTE_mm_median": float(np.median(e[:, 0])), "RRE_deg_median": float(np.median(e[:, 1])),
            "RTE_mm_mean": float(e[:, 0].mean()), "RRE_deg_mean": float(e[:, 1].mean())}
