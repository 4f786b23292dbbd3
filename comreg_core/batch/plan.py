"""What the Snakefile runs for each case: the stages, their ``comreg`` command lines, the files
they read and the status files they leave (:class:`CasePlan`).

A case's folder ``OUT/cases/<case>/`` holds ``ct_bone.stl`` (extract-ct), ``run/`` (pretrain,
when the case is pretrained here), ``us_points.ply`` (extract-us, unless ``us`` is a points
file), ``registration/`` (register, then report: ``result.json``, ``report.html``, ...),
``status/<stage>.json`` (each stage's record, :mod:`comreg_core.batch.stage`: the rule's
declared output) and ``logs/<stage>.log`` (what the command printed).
"""

from __future__ import annotations

import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

from comreg_core.batch.manifest import CASE_NAME, Case, load_manifest

#: The stages of a case, in order (``pretrain`` and ``extract_us`` only where needed).
STAGES = ("extract_ct", "pretrain", "extract_us", "register", "report")
#: The ``comreg`` command of each stage.
COMMANDS = {"extract_ct": "extract-ct", "pretrain": "pretrain", "extract_us": "extract-us",
            "register": "register", "report": "report"}
#: The stages each stage reads the outputs of (those the case runs).
NEEDS = {"extract_ct": (), "pretrain": ("extract_ct",), "extract_us": (),
         "register": ("extract_ct", "pretrain", "extract_us"), "report": ("register",)}
#: A case name in the Snakefile's output paths (its wildcard's constraint).
CASE_PATTERN = CASE_NAME.pattern
#: Where the batch writes its cohort summary (inside ``OUT``).
SUMMARY_CSV = "summary.csv"
SUMMARY_HTML = "summary.html"


@dataclass(frozen=True)
class CasePlan:
    """The stages of one case (paths absolute).

    Attributes:
        case: the manifest row; out: the batch's output folder.
        pretrain_minutes: pretraining budget of a case without a ``model`` (0: none; the case
            is then registered by the pose search alone, ``comreg register --ct``).
        preset: the pretraining preset (``cpu`` or ``paper``).
    """

    case: Case
    out: Path
    pretrain_minutes: float = 0.0
    preset: str = "cpu"

    @property
    def folder(self) -> Path:
        return self.out / "cases" / self.case.name

    @property
    def pretrains(self) -> bool:
        """Whether this case is pretrained here (a budget, and no ``model`` of its own)."""
        return self.pretrain_minutes > 0 and self.case.model is None

    @property
    def stages(self) -> list[str]:
        skip = {"pretrain"} if not self.pretrains else set()
        if self.case.us_is_points:
            skip.add("extract_us")
        return [stage for stage in STAGES if stage not in skip]

    def status(self, stage: str) -> Path:
        """The stage's status file (:mod:`comreg_core.batch.stage`)."""
        return self.folder / "status" / f"{stage}.json"

    def log(self, stage: str) -> Path:
        return self.folder / "logs" / f"{stage}.log"

    @property
    def ct_mesh(self) -> Path:
        return self.folder / "ct_bone.stl"

    @property
    def us_points(self) -> Path:
        return self.case.us if self.case.us_is_points else self.folder / "us_points.ply"

    @property
    def run_dir(self) -> Path | None:
        return self.folder / "run" if self.pretrains else self.case.model

    @property
    def registration(self) -> Path:
        return self.folder / "registration"

    def after(self, stage: str) -> list[Path]:
        """The status files of the stages ``stage`` reads from."""
        return [self.status(needed) for needed in NEEDS[stage] if needed in self.stages]

    def input_files(self, stage: str) -> list[Path]:
        """The manifest's files ``stage`` reads (a folder as the files in it), so Snakemake
        redoes the stage when one of them changes."""
        case = self.case
        given = {"extract_ct": [case.ct],
                 "pretrain": [],
                 "extract_us": [case.us, case.calibration],
                 "register": [case.us if case.us_is_points else None, case.model, case.init,
                              case.landmarks_ct, case.landmarks_us],
                 "report": []}[stage]
        return [file for path in given if path is not None for file in _files(path)]

    def outputs(self, stage: str) -> list[Path]:
        """What the stage writes (removed before it runs, so nothing stale is left)."""
        return {"extract_ct": [self.ct_mesh], "pretrain": [self.folder / "run"],
                "extract_us": [self.us_points], "register": [self.registration],
                "report": []}[stage]

    def command(self, stage: str) -> list[str]:
        """The ``comreg`` arguments of ``stage`` (without ``comreg``)."""
        case = self.case
        if stage == "extract_ct":
            picks = (["--label", str(case.label)] if case.label is not None else []) + \
                    (["--segment", case.segment] if case.segment is not None else [])
            return ["extract-ct", str(case.ct), "--out", str(self.ct_mesh), *picks]
        if stage == "pretrain":
            return ["pretrain", str(self.ct_mesh), "--out", str(self.folder / "run"),
                    "--max-minutes", f"{self.pretrain_minutes:g}", "--preset", self.preset]
        if stage == "extract_us":
            return ["extract-us", str(case.us), "--out", str(self.us_points),
                    *(["--probe-calibration", str(case.calibration)] if case.calibration else [])]
        if stage == "register":
            return self._register_command()
        if stage == "report":
            return ["report", str(self.registration)]
        raise ValueError(f"unknown stage {stage!r}")

    def _register_command(self) -> list[str]:
        case = self.case
        arguments = ["register", str(self.us_points), "--out", str(self.registration),
                     "--ct", str(self.ct_mesh)]
        if self.run_dir is not None:
            arguments += ["--model", str(self.run_dir)]
        if case.us_is_tracked_sweep:  # the report then shows its frames with the CT contour
            arguments += ["--sweep", str(case.us)]
            if case.calibration is not None:
                arguments += ["--probe-calibration", str(case.calibration)]
        if case.init is not None:
            arguments += ["--init", str(case.init)]
        if case.init_tolerance is not None:
            arguments += ["--init-tolerance", case.init_tolerance]
        if case.landmarks_ct is not None:
            arguments += ["--landmarks", str(case.landmarks_ct), str(case.landmarks_us)]
        return arguments

    def shell_command(self, stage: str, python: str = sys.executable) -> str:
        """The rule's shell command: :mod:`comreg_core.batch.stage` running the stage's
        ``comreg`` command and writing its status; output into the stage's log."""
        wrapper = [python, "-m", "comreg_core.batch.stage", "--case", self.case.name,
                   "--stage", stage, "--status", str(self.status(stage))]
        for path in self.after(stage):
            wrapper += ["--after", str(path)]
        for path in self.outputs(stage):
            wrapper += ["--fresh", str(path)]
        return f"{shlex.join([*wrapper, '--', *self.command(stage)])} > " \
               f"{shlex.quote(str(self.log(stage)))} 2>&1"


def plan_cases(manifest: str | Path, out: str | Path, *, pretrain_minutes: float = 0.0,
               preset: str = "cpu") -> dict[str, CasePlan]:
    """``{case name: CasePlan}`` for every case of the manifest (checked: a
    :class:`~comreg_core.batch.manifest.ManifestError` lists its problems)."""
    out = Path(out).absolute()
    return {case.name: CasePlan(case, out, float(pretrain_minutes), preset)
            for case in load_manifest(manifest)}


def _files(path: Path) -> list[Path]:
    """``[path]`` for a file, the files inside a folder (sorted) for a folder."""
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file() and not p.name.startswith("."))
    return [path]
