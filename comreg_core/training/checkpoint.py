"""Checkpoints and the CT fingerprint of a pretraining run.

A checkpoint (``RUN_DIR/checkpoint.pt``) is a dict of tensors, numbers and strings only (the
config as YAML text), written atomically, loadable with ``torch.load(..., weights_only=True)``:

``format`` ("comreg-checkpoint"), ``version``, ``config_yaml``, ``ct_fingerprint`` (sha256 hex),
``ct_space``, ``ct_vertices`` / ``ct_faces`` (the mesh as read, mm), ``ct_points`` (``(M, 3)``
float64 mm), ``norm_center`` (``(3,)`` float64 mm),
``norm_scale`` (mm), ``model`` (state dict), ``optimizer_backbone``, ``optimizer_head``,
``scheduler_backbone``, ``scheduler_head`` (state dicts), ``epoch`` (completed epochs), ``step``
(steps done in the current epoch), ``samples_seen``, ``elapsed_s`` (training time so far),
``epoch_sums`` (running loss sums of the current epoch, means over all processes),
``world_size`` (processes that wrote it; older checkpoints: absent, 1). No random generator
state: every step seeds its own (:func:`~comreg_core.training.data.step_torch_seed`), so a run
resumes the same way at any number of processes. Rank 0 alone writes it.
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path
from typing import Any

import torch

from comreg_core import runs
from comreg_core.errors import ComRegError
from comreg_core.io.meshes import ct_fingerprint, mesh_fingerprint  # noqa: F401 (re-exported)
from comreg_core.io._files import atomic_output
from comreg_core.io.json_files import write_json

CHECKPOINT_FORMAT = "comreg-checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(ComRegError):
    """A run folder or checkpoint is missing, unreadable, or was made for another CT."""


def write_fingerprint(fingerprint: dict[str, Any], run_dir: Path) -> Path:
    path = Path(run_dir) / runs.FINGERPRINT
    return write_json(fingerprint, path)


def save_checkpoint(state: dict[str, Any], path: str | Path) -> Path:
    """Write ``state`` atomically (a killed write leaves the previous checkpoint intact)."""
    state = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **state}
    path = Path(path)
    with atomic_output(path) as tmp:
        torch.save(state, tmp)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu"
                    ) -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True`` (never runs code from the file)."""
    path = Path(path)
    if path.is_dir():
        path = path / runs.CHECKPOINT
    if not path.is_file():
        raise CheckpointError(f"No checkpoint at '{path}'.",
                              "Pass the folder written by 'comreg pretrain' (it holds "
                              f"{runs.CHECKPOINT}), or train one first.")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except MemoryError:
        raise
    except Exception as exc:  # unpickling errors of every kind: the file is not ours or broken
        # torch's own text is not quoted: it suggests weights_only=False, which would run code
        # from the file; ComReg never does that.
        what = ("is not a plain file of tensors, numbers and strings"
                if isinstance(exc, pickle.UnpicklingError) else "cannot be unpacked")
        raise CheckpointError(f"Cannot read the checkpoint '{path}': it {what} "
                              f"({type(exc).__name__}).",
                              "The file is corrupt, truncated or not a ComReg checkpoint "
                              "(ComReg never runs code from a file); train again or resume from "
                              "an intact run.") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"'{path}' is not a ComReg checkpoint.",
                              "Pass the checkpoint written by 'comreg pretrain'.")
    if int(state.get("version", 0)) > CHECKPOINT_VERSION:
        raise CheckpointError(f"'{path}' was written by a newer ComReg (checkpoint version "
                              f"{state['version']}).", "Update ComReg.")
    check_state(state, path)
    return state


# --- validation of what a checkpoint holds -------------------------------------------------------

#: Entries every checkpoint holds, with their type.
_REQUIRED = {"config_yaml": str, "ct_fingerprint": str, "ct_vertices": torch.Tensor,
             "ct_faces": torch.Tensor, "ct_points": torch.Tensor, "norm_center": torch.Tensor,
             "norm_scale": (float, int), "model": dict}


def check_state(state: dict[str, Any], path: str | Path = "checkpoint") -> None:
    """Raise :class:`CheckpointError` unless a loaded checkpoint holds what a registration needs:
    every entry of the right type, CT arrays of the right shapes, finite numbers, a positive
    scale and finite network weights (a diverged or tampered run holds NaN or inf)."""
    def broken(detail: str) -> CheckpointError:
        return CheckpointError(f"The checkpoint '{path}' is unusable: {detail}.",
                               "Train again (comreg pretrain), or resume from an intact run.")

    for key, kind in _REQUIRED.items():
        if not isinstance(state.get(key), kind):
            raise broken(f"its entry '{key}' is missing or of the wrong type")
    for key, width in (("ct_vertices", 3), ("ct_faces", 3), ("ct_points", 3)):
        t = state[key]
        if t.ndim != 2 or t.shape[1] != width or t.shape[0] == 0:
            raise broken(f"'{key}' has shape {tuple(t.shape)}, expected (N, {width})")
    if tuple(state["norm_center"].shape) != (3,):
        raise broken(f"'norm_center' has shape {tuple(state['norm_center'].shape)}")
    for key in ("ct_vertices", "ct_points", "norm_center"):
        if not bool(torch.isfinite(state[key]).all()):
            raise broken(f"'{key}' holds NaN or infinite values")
    faces = state["ct_faces"]
    if faces.is_floating_point() or int(faces.min()) < 0 or \
            int(faces.max()) >= len(state["ct_vertices"]):
        raise broken("'ct_faces' index vertices that do not exist")
    scale = float(state["norm_scale"])
    if not (math.isfinite(scale) and scale > 0):
        raise broken(f"'norm_scale' is {scale}, not a positive length")
    for name, tensor in state["model"].items():
        if not isinstance(tensor, torch.Tensor):
            raise broken(f"the network entry '{name}' is not a tensor")
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise broken(f"the network weights '{name}' hold NaN or infinite values (a diverged "
                         "or damaged training)")


def check_fingerprint(expected: str, actual: dict[str, Any] | str, where: str = "") -> None:
    """Raise :class:`CheckpointError` unless the CT fingerprints match."""
    sha = actual if isinstance(actual, str) else actual["sha256"]
    if sha != expected:
        raise CheckpointError(
            f"The checkpoint{where} was trained for another CT (CT fingerprint {expected[:12]}… "
            f"!= {sha[:12]}… of the given mesh).",
            "Register against the CT the model was pretrained on, or pretrain a model for this "
            "CT with 'comreg pretrain'.")


#: A given CT mesh is the run's bone when its surface and the run's stored one lie within this
#: distance (mm) of each other at the 95th percentile, both ways
#: (:func:`~comreg_core.registration.geometry.metrics.surface_disagreement_mm`). Measured: the shared
#: fibula STL against the bundled model's CT (the same bone extracted again from its
#: segmentation) 0.23 mm; the same bone moved 2 mm: ~2 mm; another bone: tens of mm. Well below
#: the 4 mm of a failed registration, so a mesh that passes cannot move a result noticeably.
SAME_BONE_TOLERANCE_MM = 1.0


def check_same_bone(state: dict[str, Any], ct_mesh, where: str = "") -> float:
    """Raise :class:`CheckpointError` unless ``ct_mesh`` (path or SurfaceMesh) is the bone the
    checkpoint ``state`` was trained for: the identical mesh (sha256 fingerprint) or the same
    surface re-meshed or written by another tool (in either patient space), within
    :data:`SAME_BONE_TOLERANCE_MM`. Returns the surfaces' disagreement (mm; 0.0 when identical)."""
    from comreg_core.io.meshes import SurfaceMesh, read_mesh
    from comreg_core.registration.geometry.metrics import surface_disagreement_mm

    mesh = ct_mesh if isinstance(ct_mesh, SurfaceMesh) else read_mesh(ct_mesh)
    if ct_fingerprint(mesh.vertices, mesh.faces)["sha256"] == state["ct_fingerprint"]:
        return 0.0
    space = str(state.get("ct_space", "LPS"))
    stored = (state["ct_vertices"].numpy(), state["ct_faces"].numpy())
    gap = surface_disagreement_mm(stored, mesh.in_space(space))
    if not gap <= SAME_BONE_TOLERANCE_MM:
        raise CheckpointError(
            f"The checkpoint{where} was trained for another CT: the given mesh lies {gap:.1f} mm "
            f"from the run's CT bone (95th percentile; the same bone re-meshed is within "
            f"{SAME_BONE_TOLERANCE_MM:g} mm).",
            "Register against the CT the model was pretrained on (in the same place), or "
            "pretrain a model for this CT with 'comreg pretrain'.")
    return gap


def run_ct_mesh(run_dir: str | Path):
    """The CT bone mesh a run was trained on, from its checkpoint (a :class:`SurfaceMesh` in the
    CT's patient space): the run stays usable even if the original mesh file moved."""
    from comreg_core.io.meshes import SurfaceMesh

    state = load_checkpoint(run_dir)
    return SurfaceMesh(state["ct_vertices"].numpy(), state["ct_faces"].numpy(),
                       str(state.get("ct_space", "LPS")))


#: Checkpoint entries a registration needs (no optimiser, scheduler or RNG state).
MODEL_ENTRIES = ("config_yaml", "ct_fingerprint", "ct_space", "ct_vertices", "ct_faces",
                 "ct_points", "norm_center", "norm_scale", "epoch", "samples_seen", "elapsed_s",
                 "validation", "validation_epoch", "initial_error")

#: The network counts as not having learned while its coarse rotation halves the initial error
#: on fewer than this share of the validation sweeps (``val_coarse_improved_share``).
NOT_LEARNED_IMPROVED_SHARE = 0.1

#: Runs validated before that share was logged: the network counts as not having learned while
#: its validation coarse RRE (median) is above this share of the validation set's initial
#: misalignment (median RRE of doing nothing).
NOT_LEARNED_RRE_SHARE = 0.75


def network_warning(state: dict[str, Any]) -> str | None:
    """A one-line warning when a checkpoint's own validation says its network has not learned
    the pose (its coarse rotation halves the initial error on fewer than
    :data:`NOT_LEARNED_IMPROVED_SHARE` of the validation sweeps; for older runs: coarse RRE
    median above :data:`NOT_LEARNED_RRE_SHARE` of the initial poses'), or when it has no
    training or validation to judge by; None when it has learned."""
    epochs = int(state.get("epoch", 0))
    if epochs == 0:
        return ("The network has not been trained (0 epochs): its pose is a guess; only the "
                "pose search can make the result right.")
    validation, initial = state.get("validation"), state.get("initial_error")
    if not validation or not initial:
        return None  # written before validation was stored: nothing to judge by
    coarse = float(validation["val_coarse_RRE_deg_median"])
    start = float(initial["RRE_deg_median"])
    share = validation.get("val_coarse_improved_share")
    if share is None:
        learned = coarse <= NOT_LEARNED_RRE_SHARE * start
        how = f"is no better than the initial poses' ({start:.0f} deg)"
    else:
        learned = float(share) >= NOT_LEARNED_IMPROVED_SHARE
        how = (f"halves the initial poses' ({start:.0f} deg) on only {float(share):.0%} of the "
               "validation sweeps")
    if learned:
        return None
    return (f"The network has not learned the pose: after {epochs} epochs its validation "
            f"coarse rotation error (median {coarse:.0f} deg) {how}; the result rests on the "
            "pose search. Train longer.")


def export_model(run_dir: str | Path, path: str | Path, *, half: bool = True) -> Path:
    """Write a registration-only copy of a run's checkpoint (e.g. to ship a model).

    Keeps the network weights (as float16 when ``half``: half the size, registration results
    change by far less than a millimetre), the config, the CT mesh, cloud, fingerprint and
    normalisation; leaves out the optimiser and scheduler state, so the copy cannot be resumed.
    :meth:`comreg_core.register.Registrar.from_run` loads it like a run folder.
    """
    state = load_checkpoint(run_dir)
    slim = {key: state[key] for key in MODEL_ENTRIES if key in state}
    slim["model"] = {name: (t.half() if half and t.is_floating_point() else t)
                     for name, t in state["model"].items()}
    return save_checkpoint(slim, path)
