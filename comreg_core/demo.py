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

import numpy as np

from comreg_core import runs
from comreg_core.errors import ComRegError
from comreg_core.io._files import check_output_folder
from comreg_core.io.json_files import write_json

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
    from comreg_core.evaluation.evaluate import evaluate, write_metrics
    from comreg_core.registration.geometry.metrics import (registration_metrics,
                                                           rotation_error_deg,
                                                           translation_error_mm)
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.register import Registrar
    from comreg_core.register import register_to_directory
    from comreg_core.io import PointCloud, read_mesh, save_transform, write_points
    from comreg_core.report import write_report_for_registration
    from comreg_core.simulation import sample_initial_pose
    from comreg_core.surfaces.us import extract_us_to_file
    from comreg_core.transforms import apply_transform, invert_rigid

    step = step or (lambda line: log.info("%s", line))
    _sample_files()
    out = check_output_folder(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    step(f"extracting the CT bone surface from {SAMPLE_SEGMENTATION.name}")
    ct_path = write_sample_ct_surface(out / "ct_bone.stl")
    ct = read_mesh(ct_path)  # as stored (STL keeps float32 vertices): the CT the model knows

    step(f"finding the bone in the {SAMPLE_SWEEP.name} frames")
    us = extract_us_to_file(SAMPLE_SWEEP, out / "us_points.ply")
    us_points = PointCloud(us.points.points, "LPS").in_space(ct.space).points

    model, trained = _model_for(ct_path, out, device, train_minutes, step)

    step(f"finding the truth: {TRUTH}")
    surface = CTSurface(ct)  # shared by the truth, the errors and the evaluation
    T_truth = pseudo_ground_truth(us_points, surface)  # recorded tracking: identity
    centroid = us_points.mean(axis=0)
    tracking = {"RTE_mm": translation_error_mm(np.eye(4), T_truth, centroid),
                "RRE_deg": rotation_error_deg(np.eye(4), T_truth)}

    rng = np.random.default_rng(seed)
    T_moved_ct = sample_initial_pose(rng, "paper", center=centroid)
    T_ct_us_truth = T_truth @ invert_rigid(T_moved_ct)
    moved = apply_transform(T_moved_ct, us_points)
    moved_path = write_points(PointCloud(moved, ct.space), out / "us_points_moved.ply")
    save_transform(T_ct_us_truth, out / "T_ct_us_truth.tfm", space=ct.space)

    step("registering the moved US points to the CT (completion, coarse pose, ICP)")
    registration_dir = out / "registration"
    result = register_to_directory(model, moved_path, registration_dir, device=device,
                                   seed=seed, ct_mesh=ct_path, sweep=SAMPLE_SWEEP,
                                   T_us_ref=T_moved_ct)  # tracking and CT share one frame
    errors = registration_metrics(result.T_ct_us, T_ct_us_truth, moved, surface)
    verdict = json.loads((registration_dir / runs.RESULT).read_text(encoding="utf-8"))["verdict"]
    success_rate = flip_rate = search_success_rate = search_flip_rate = None
    # "registration.T_ct_us" marks metrics.json as made for this registration (the report
    # shows no other), with its errors against the truth, what that is, and the tracking's
    metrics = {"registration": {"T_ct_us": result.T_ct_us.tolist(), "errors_vs_truth": errors,
                                "truth": TRUTH, "T_ct_recorded": T_truth.tolist(),
                                "tracking_vs_truth": tracking}}
    if trials > 0:
        step(f"evaluating {trials} more random starts")
        methods = {"search": Registrar.from_ct(ct),
                   "comreg": Registrar.from_run(model, device, ct_mesh=ct)}
        metrics.update(evaluate(methods, us_points, surface, trials=trials, seed=seed,
                                T_gt=T_truth))
        summary = metrics["summary"]
        success_rate, flip_rate = (summary["comreg"][k] for k in ("success_rate", "flip_rate"))
        search_success_rate, search_flip_rate = (summary["search"][k]
                                                 for k in ("success_rate", "flip_rate"))
    write_metrics(metrics, registration_dir / runs.METRICS)

    step("rendering the report")
    report = write_report_for_registration(registration_dir, ct_mesh=ct_path)
    demo = DemoResult(out, report, Path(model), trained, result.n_points, errors["RTE_mm"],
                      errors["RRE_deg"], result.runtime_s, success_rate, flip_rate,
                      bool(errors["success"]), verdict, tracking["RTE_mm"], tracking["RRE_deg"],
                      search_success_rate, search_flip_rate)
    summary = {"RTE_mm": demo.RTE_mm, "RRE_deg": demo.RRE_deg, "success": demo.success,
               "verdict": demo.verdict, "truth": TRUTH, "tracking_vs_truth": tracking,
               "runtime_s": demo.runtime_s, "model": str(model), "trained": trained,
               "n_us_points": demo.n_us_points, "success_rate": success_rate,
               "flip_rate": flip_rate, "search_success_rate": search_success_rate,
               "search_flip_rate": search_flip_rate, "report": str(report)}
    write_json(summary, out / "demo.json")
    return demo
