"""``comreg demo``: the whole job on the bundled sample case, from files to a report.

The sample (``resources/sample``, CC BY 4.0, UltraBones100k, Wu et al. 2025) is a cadaver fibula:
``fibula.seg.nrrd`` (its CT bone as a 3D Slicer segmentation), ``sweep/`` (37 frames of its real
tracked freehand sweep, see ``scripts/make_sample_sweep.py``) and ``fibula_cpu.pt`` (a ``cpu``
preset model pretrained by this project on simulated sweeps of the surface extracted from that
segmentation, see ``scripts/make_sample_checkpoint.py``). CT and tracking share one frame, so the
recorded tracking puts the sweep's points near the CT bone, but not on it: the recording has its
own error (tracking, calibration, the CT's segmentation). As the paper does, the demo's truth is
therefore a pseudo ground truth: ICP of the points to the CT started from the recorded tracking
(:func:`pseudo_ground_truth`, the evaluation's ``icp-gt`` baseline). The registration, its
success and the further random starts are all measured against it, and the demo says how far the
recorded tracking itself lies from it.

:func:`run_demo` writes into ``out_dir``:

1. ``ct_bone.stl``: the CT bone surface extracted from the segmentation;
2. ``us_points.ply``: the bone points found in the US frames (CT frame);
3. ``us_points_moved.ply``: the same points moved by a known rigid misalignment (the paper's
   perturbation: up to 90 deg about one axis and 100 mm, drawn from ``seed``), as if tracked in
   another frame; ``T_ct_us_truth.tfm`` undoes it and then applies the pseudo ground truth;
4. ``registration/``: ``comreg register`` of the moved points (``result.json``, ``transform.tfm``,
   ``registered_us.ply``, ``completion_ct.ply``), ``metrics.json`` (this registration's errors
   against the truth, what the truth is and how far the recorded tracking lies from it, and
   ``comreg evaluate`` of ``trials`` more random starts of the same cloud, against the same
   truth) and ``report.html`` with its verdict, those errors and its screenshots;
5. ``demo.json``: the figures of :class:`DemoResult`.

Without the bundled model, or when it does not fit the extracted surface (another VTK gives
another mesh), a model is pretrained first into ``out_dir/run`` for ``train_minutes``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from comreg_core import runs
from comreg_core.errors import ComRegError
from comreg_core.io._files import check_output_folder
from comreg_core.io.json_files import write_json

if TYPE_CHECKING:
    from comreg_core.io.meshes import SurfaceMesh
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.registration.search.result import RegistrationResult

log = logging.getLogger(__name__)

#: The bundled sample case.
SAMPLE_DIR = Path(__file__).resolve().parents[1] / "resources" / "sample"
SAMPLE_SEGMENTATION = SAMPLE_DIR / "fibula.seg.nrrd"
SAMPLE_SWEEP = SAMPLE_DIR / "sweep"
SAMPLE_MODEL = SAMPLE_DIR / "fibula_cpu.pt"

#: Called with a line saying what the demo does next.
Step = Callable[[str], None]

#: What the demo measures its errors against, in words (the report and the summary say it).
TRUTH = "ICP from the recorded tracking (pseudo ground truth, as in the paper)"


@dataclass
class DemoResult:
    """What :func:`run_demo` did.

    Attributes:
        out_dir: the demo folder; report: its ``registration/report.html``.
        model: the checkpoint used (bundled or freshly trained).
        trained: whether a model was trained in this run.
        n_us_points: US bone points extracted from the sweep.
        RTE_mm, RRE_deg: error of the registration shown in the report, against the truth
            (:data:`TRUTH`).
        success: whether that error is a success (RTE < 2 mm and RRE < 2 deg).
        verdict: the registration's verdict, ``"ok"`` or ``"check"`` (from its files alone).
        tracking_RTE_mm, tracking_RRE_deg: how far the recorded tracking lies from the truth.
        runtime_s: its registration time (s).
        success_rate, flip_rate: over the ``trials`` extra random starts, with the network
            (None if 0 trials).
        search_success_rate, search_flip_rate: the same starts by the pose search alone (the
            network's control: what the network adds is the difference).
        truth: what the errors are measured against, in words.
    """

    out_dir: Path
    report: Path
    model: Path
    trained: bool
    n_us_points: int
    RTE_mm: float
    RRE_deg: float
    runtime_s: float
    success_rate: float | None
    flip_rate: float | None
    success: bool
    verdict: str
    tracking_RTE_mm: float
    tracking_RRE_deg: float
    search_success_rate: float | None = None
    search_flip_rate: float | None = None
    truth: str = TRUTH


def summary_lines(result: DemoResult, trials: int) -> list[str]:
    """What ``comreg demo`` prints at the end: the registration's error against the truth, its
    success and verdict, what the truth is, the further starts and the report."""
    lines = [f"registered {result.n_us_points} US points in {result.runtime_s:.2f} s: error "
             f"{result.RTE_mm:.2f} mm, {result.RRE_deg:.2f} deg, success "
             f"{'yes' if result.success else 'no'}; Verdict: {result.verdict.upper()}",
             f"truth: {result.truth}; the tracking itself lies {result.tracking_RTE_mm:.2f} mm "
             f"/ {result.tracking_RRE_deg:.2f}° from it"]
    if result.success_rate is not None:
        lines.append(f"{trials} more random starts: with the network success "
                     f"{result.success_rate:.0%}, flips {result.flip_rate:.0%}; the search alone "
                     f"success {result.search_success_rate:.0%}, flips "
                     f"{result.search_flip_rate:.0%}")
    lines.append(f"report: {result.report}")
    return lines


def pseudo_ground_truth(us_points: np.ndarray, ct, T_ct_us_recorded: np.ndarray | None = None
                        ) -> np.ndarray:
    """The paper's pseudo ground truth of a recorded sweep: ``T_ct_us`` from the evaluation's
    ``icp-gt`` baseline (:class:`~comreg_core.evaluation.baselines.IcpGtBaseline`, point-to-plane
    ICP to the CT mesh with its default settings) started from the recorded tracking
    ``T_ct_us_recorded`` (identity: CT and tracking in one frame)."""
    from comreg_core.evaluation.baselines import IcpGtBaseline

    start = np.eye(4) if T_ct_us_recorded is None else T_ct_us_recorded
    return IcpGtBaseline(ct)(us_points, start).T_ct_us


def _sample_files() -> None:
    for path in (SAMPLE_SEGMENTATION, SAMPLE_SWEEP):
        if not path.exists():
            raise ComRegError(f"The bundled sample '{path}' is missing.",
                              "Run the demo from a full checkout of ComReg (resources/sample).")


def write_sample_ct_surface(path: str | Path) -> Path:
    """Extract the sample's CT bone surface (default options) and write it to ``path``: the mesh
    the bundled model was trained for (``scripts/make_sample_checkpoint.py`` uses it too)."""
    from comreg_core.io import read_segmentation, write_mesh
    from comreg_core.surfaces.ct import extract_bone_surface

    _sample_files()
    return write_mesh(extract_bone_surface(read_segmentation(SAMPLE_SEGMENTATION),
                                           name="fibula"), path)


def _model_for(ct_path: Path, out_dir: Path, device: str, train_minutes: float,
               step: Step) -> tuple[Path, bool]:
    """The bundled model if it was trained for this CT surface, else a freshly trained run."""
    from comreg_core.io import read_mesh
    from comreg_core.training import load_checkpoint, mesh_fingerprint, pretrain

    fingerprint = mesh_fingerprint(read_mesh(ct_path))["sha256"]
    if SAMPLE_MODEL.is_file():
        if load_checkpoint(SAMPLE_MODEL)["ct_fingerprint"] == fingerprint:
            return SAMPLE_MODEL, False
        log.warning("The bundled model '%s' was trained for another CT surface (this VTK "
                    "extracts a slightly different mesh); training a new one", SAMPLE_MODEL)
    run_dir = out_dir / "run"
    if (run_dir / runs.CHECKPOINT).is_file():
        try:
            if load_checkpoint(run_dir)["ct_fingerprint"] == fingerprint:
                return run_dir, False
        except ComRegError:
            pass
        raise ComRegError(f"'{run_dir}' holds a run for another CT or a broken checkpoint.",
                          "Delete it or choose another --out.")
    step(f"pretraining a cpu model for {train_minutes:g} min (no bundled model fits)")
    pretrain(ct_path, run_dir, preset="cpu", max_minutes=train_minutes, device=device)
    return run_dir, True


@dataclass(frozen=True)
class _Truth:
    """What the demo measures against: ``surface`` (the CT surface shared by the truth, the
    errors and the evaluation), ``T_ct_us`` ``(4, 4)`` (the pseudo ground truth of the sweep's
    points) and ``tracking`` (the recorded tracking's ``RTE_mm`` and ``RRE_deg`` from it)."""

    surface: CTSurface
    T_ct_us: np.ndarray
    tracking: dict[str, float]


@dataclass(frozen=True)
class _Moved:
    """The sweep's points under a known misalignment: ``T_moved_ct`` ``(4, 4)`` moves them,
    ``points`` ``(N, 3)`` (mm) are the moved points, written to ``path``, and ``T_ct_us_truth``
    ``(4, 4)`` maps them back onto the truth."""

    T_moved_ct: np.ndarray
    T_ct_us_truth: np.ndarray
    points: np.ndarray
    path: Path


def run_demo(out_dir: str | Path = "out/demo", *, device: str = "auto",
             train_minutes: float = 10.0, trials: int = 10, seed: int = 0,
             step: Step | None = None) -> DemoResult:
    """Run the sample case end to end (module docstring); returns a :class:`DemoResult`.

    Args:
        out_dir: output folder (created; files in it are replaced).
        device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
        train_minutes: time budget of the pretraining, if one is needed.
        trials: extra random starts evaluated into ``metrics.json`` (0 = none).
        seed: seed of the misalignment and of the trials.
        step: called with a line before each stage (the CLI prints it).
    """
    from comreg_core.evaluation.evaluate import write_metrics
    from comreg_core.report import write_report_for_registration
    from comreg_core.training.trainer import resolve_device

    step = step or (lambda line: log.info("%s", line))
    _sample_files()
    resolve_device(device)  # "cuda" without CUDA: refused before any file is written
    out = check_output_folder(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ct_path, ct, us_points = _extract_inputs(out, step)
    model, trained = _model_for(ct_path, out, device, train_minutes, step)
    truth = _find_truth(us_points, ct, step)
    moved = _misalign(us_points, truth, ct.space, out, seed)
    registration_dir = out / "registration"
    result, errors, verdict = _register(model, moved, truth, ct_path, registration_dir,
                                        device=device, seed=seed, step=step)
    # "registration.T_ct_us" marks metrics.json as made for this registration (the report
    # shows no other), with its errors against the truth, what that is, and the tracking's
    metrics = {"registration": {"T_ct_us": result.T_ct_us.tolist(), "errors_vs_truth": errors,
                                "truth": TRUTH, "T_ct_recorded": truth.T_ct_us.tolist(),
                                "tracking_vs_truth": truth.tracking}}
    success_rate, flip_rate, search_success_rate, search_flip_rate = _evaluate_starts(
        metrics, us_points, ct, truth, model, device=device, trials=trials, seed=seed, step=step)
    write_metrics(metrics, registration_dir / runs.METRICS)

    step("rendering the report")
    report = write_report_for_registration(registration_dir, ct_mesh=ct_path)
    demo = DemoResult(out, report, Path(model), trained, result.n_points, errors["RTE_mm"],
                      errors["RRE_deg"], result.runtime_s, success_rate, flip_rate,
                      bool(errors["success"]), verdict, truth.tracking["RTE_mm"],
                      truth.tracking["RRE_deg"], search_success_rate, search_flip_rate)
    _write_summary(demo, truth, model, out / "demo.json")
    return demo


def _extract_inputs(out: Path, step: Step) -> tuple[Path, SurfaceMesh, np.ndarray]:
    """The sample's CT bone surface as ``out/ct_bone.stl`` (its path and the mesh as stored: STL
    keeps float32 vertices, the CT the model knows) and the bone points found in its sweep's
    frames as ``out/us_points.ply`` (``(N, 3)`` mm, in the CT's space)."""
    from comreg_core.io import PointCloud, read_mesh
    from comreg_core.surfaces.us import extract_us_to_file

    step(f"extracting the CT bone surface from {SAMPLE_SEGMENTATION.name}")
    ct_path = write_sample_ct_surface(out / "ct_bone.stl")
    ct = read_mesh(ct_path)

    step(f"finding the bone in the {SAMPLE_SWEEP.name} frames")
    us = extract_us_to_file(SAMPLE_SWEEP, out / "us_points.ply")
    return ct_path, ct, PointCloud(us.points.points, "LPS").in_space(ct.space).points


def _find_truth(us_points: np.ndarray, ct: SurfaceMesh, step: Step) -> _Truth:
    """The pseudo ground truth of ``us_points`` (recorded tracking: identity) and how far the
    recorded tracking lies from it."""
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from comreg_core.registration.geometry.surface import CTSurface

    step(f"finding the truth: {TRUTH}")
    surface = CTSurface(ct)
    T_truth = pseudo_ground_truth(us_points, surface)
    centroid = us_points.mean(axis=0)
    return _Truth(surface, T_truth,
                  {"RTE_mm": translation_error_mm(np.eye(4), T_truth, centroid),
                   "RRE_deg": rotation_error_deg(np.eye(4), T_truth)})


def _misalign(us_points: np.ndarray, truth: _Truth, space: str, out: Path, seed: int) -> _Moved:
    """Move ``us_points`` by the paper's random perturbation (drawn from ``seed``) about their
    centroid; writes ``us_points_moved.ply`` and ``T_ct_us_truth.tfm`` into ``out``."""
    from comreg_core.io import PointCloud, save_transform, write_points
    from comreg_core.simulation import sample_initial_pose
    from comreg_core.transforms import apply_transform, invert_rigid

    rng = np.random.default_rng(seed)
    T_moved_ct = sample_initial_pose(rng, "paper", center=us_points.mean(axis=0))
    T_ct_us_truth = truth.T_ct_us @ invert_rigid(T_moved_ct)
    moved = apply_transform(T_moved_ct, us_points)
    moved_path = write_points(PointCloud(moved, space), out / "us_points_moved.ply")
    save_transform(T_ct_us_truth, out / "T_ct_us_truth.tfm", space=space)
    return _Moved(T_moved_ct, T_ct_us_truth, moved, moved_path)


def _register(model: Path, moved: _Moved, truth: _Truth, ct_path: Path, registration_dir: Path,
              *, device: str, seed: int, step: Step
              ) -> tuple[RegistrationResult, dict[str, Any], str]:
    """``comreg register`` of the moved points into ``registration_dir``: its result, its
    errors against the truth and its verdict (``"ok"``/``"check"``, read from its files)."""
    from comreg_core.register import register_to_directory
    from comreg_core.registration.geometry.metrics import registration_metrics

    step("registering the moved US points to the CT (completion, coarse pose, ICP)")
    result = register_to_directory(model, moved.path, registration_dir, device=device,
                                   seed=seed, ct_mesh=ct_path, sweep=SAMPLE_SWEEP,
                                   T_us_ref=moved.T_moved_ct)  # tracking and CT share one frame
    errors = registration_metrics(result.T_ct_us, moved.T_ct_us_truth, moved.points,
                                  truth.surface)
    verdict = json.loads((registration_dir / runs.RESULT).read_text(encoding="utf-8"))["verdict"]
    return result, errors, verdict


def _evaluate_starts(metrics: dict[str, Any], us_points: np.ndarray, ct: SurfaceMesh, truth: _Truth,
                     model: Path, *, device: str, trials: int, seed: int, step: Step
                     ) -> tuple[float | None, float | None, float | None, float | None]:
    """``comreg evaluate`` of ``trials`` random starts of ``us_points``, with the network and by
    the search alone, added to ``metrics``; the success and flip rates of both (None when
    ``trials`` is 0)."""
    from comreg_core.evaluation.evaluate import evaluate
    from comreg_core.register import Registrar

    if trials <= 0:
        return None, None, None, None
    step(f"evaluating {trials} more random starts")
    methods = {"search": Registrar.from_ct(ct),
               "comreg": Registrar.from_run(model, device, ct_mesh=ct)}
    metrics.update(evaluate(methods, us_points, truth.surface, trials=trials, seed=seed,
                            T_gt=truth.T_ct_us))
    summary = metrics["summary"]
    return (summary["comreg"]["success_rate"], summary["comreg"]["flip_rate"],
            summary["search"]["success_rate"], summary["search"]["flip_rate"])


def _write_summary(demo: DemoResult, truth: _Truth, model: Path, path: Path) -> None:
    """The figures of ``demo`` as ``demo.json``."""
    write_json({"RTE_mm": demo.RTE_mm, "RRE_deg": demo.RRE_deg, "success": demo.success,
                "verdict": demo.verdict, "truth": TRUTH, "tracking_vs_truth": truth.tracking,
                "runtime_s": demo.runtime_s, "model": str(model), "trained": demo.trained,
                "n_us_points": demo.n_us_points, "success_rate": demo.success_rate,
                "flip_rate": demo.flip_rate, "search_success_rate": demo.search_success_rate,
                "search_flip_rate": demo.search_flip_rate, "report": str(demo.report)}, path)
