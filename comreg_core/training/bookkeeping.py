"""The training loop's bookkeeping: where a run is, its clocks, its epoch log.

:class:`Tally` is the loop's state that a checkpoint saves and a resumed run restores (epochs,
steps, samples, training time, the epoch's loss sums, the last validation). :class:`Clock` holds
the time budget and the latest durations of a step, a validation and a checkpoint (seconds,
``time.monotonic``). :class:`EpochLog` is ``training_log.csv`` (:data:`LOG_COLUMNS`).
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from comreg_core.io._files import atomic_output
from comreg_core.training.step import LOSS_TERMS

#: Columns of ``training_log.csv`` (losses are epoch means; ``val_*`` empty when not validated).
LOG_COLUMNS = (
    "epoch", "samples", "world_size", "time_s", "epoch_s", "lr_backbone", "lr_head", "loss",
    "completion", "sparse", "dense", "registration", "reg_coarse", "reg_fine", "correspondence",
    "skipped_steps", "val_RTE_mm_median", "val_RRE_deg_median", "val_RTE_mm_mean",
    "val_RRE_deg_mean", "val_coarse_RTE_mm_median", "val_coarse_RRE_deg_median",
    "val_coarse_improved_share", "val_success_rate", "val_flip_rate", "val_loss", "val_completion",
    "val_completion_CD_mm_median", "val_s",
)


@dataclass
class Tally:
    """Where the loop is.

    Attributes:
        epoch: completed epochs. step: steps done in the current epoch.
        samples_seen: training samples consumed in total.
        elapsed_s: training time of the invocations before this one (s).
        sums: running sums of the current epoch's losses (:data:`LOSS_TERMS`), ``steps`` and
            ``skipped`` (steps with a non-finite loss).
        validation, validation_epoch: the last validation (``val_*`` figures) and its epoch.
        losses: epoch means of the last epoch this invocation completed.
    """

    epoch: int = 0
    step: int = 0
    samples_seen: int = 0
    elapsed_s: float = 0.0
    sums: dict[str, float] = field(default_factory=dict)
    validation: dict[str, float] | None = None
    validation_epoch: int = 0
    losses: dict[str, float] = field(default_factory=dict)

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any]) -> Tally:
        """The tally a checkpoint stored."""
        tally = cls(int(state["epoch"]), int(state["step"]), int(state["samples_seen"]),
                    float(state["elapsed_s"]),
                    {k: float(v) for k, v in state["epoch_sums"].items()})
        if "validation" in state:
            tally.validation = {k: float(v) for k, v in state["validation"].items()}
            tally.validation_epoch = int(state["validation_epoch"])
        return tally

    def add_step(self, losses: dict[str, float], applied: bool, batch_size: int) -> None:
        """Count one step of ``batch_size`` samples: its losses when it was applied, a skipped
        step otherwise."""
        if applied:
            for name in LOSS_TERMS:
                self.sums[name] = self.sums.get(name, 0.0) + losses[name]
            self.sums["steps"] = self.sums.get("steps", 0.0) + 1
        else:
            self.sums["skipped"] = self.sums.get("skipped", 0.0) + 1
        self.step += 1
        self.samples_seen += batch_size

    def close_epoch(self) -> int:
        """End the epoch: its loss means into :attr:`losses`, the sums emptied; returns the
        number of skipped steps."""
        self.epoch += 1
        self.step = 0
        n = max(self.sums.get("steps", 0.0), 1.0)
        self.losses = {k: self.sums.get(k, 0.0) / n for k in LOSS_TERMS}
        skipped = int(self.sums.get("skipped", 0))
        self.sums = {}
        return skipped


class Clock:
    """The time budget of one invocation, the training time of the run, and when the epoch and
    the checkpoint interval started (``time.monotonic``, s).

    Args:
        command_start: ``time.monotonic()`` when the command started (the budget counts from it).
        max_minutes: the budget (0 = none).
        elapsed_s: training time of earlier invocations (s); this one's counts from now.
    """

    def __init__(self, command_start: float, max_minutes: float, elapsed_s: float):
        self.command_start = command_start
        self.budget_s = max_minutes * 60.0 if max_minutes > 0 else math.inf
        self.cost = {"step": 0.0, "validation": 0.0, "checkpoint": 0.0}  # latest, s
        self.before_s = elapsed_s
        self.start = time.monotonic()
        self.last_checkpoint = self.epoch_start = math.nan  # set by start_epochs

    def start_epochs(self) -> None:
        """Start the checkpoint interval and the first epoch's time."""
        self.last_checkpoint = time.monotonic()
        self.epoch_start = time.monotonic()

    def elapsed(self) -> float:
        """Training time of the run so far (s)."""
        return self.before_s + (time.monotonic() - self.start)

    @contextmanager
    def timed(self, what: str) -> Iterator[None]:
        """Record the duration of the block as the latest ``cost[what]`` (not when it raises)."""
        mark = time.monotonic()
        yield
        self.cost[what] = time.monotonic() - mark

    def runs_out(self, ends_epoch: bool) -> bool:
        """Whether the next step (with the validation ending the epoch, and a checkpoint) would
        end after the budget."""
        left = self.budget_s - (time.monotonic() - self.command_start)
        need = (self.cost["step"] + self.cost["checkpoint"]
                + (self.cost["validation"] if ends_epoch else 0.0))
        return left < need

    def since_command(self) -> float:
        """Seconds since the command started."""
        return time.monotonic() - self.command_start

    def epoch_seconds(self) -> float:
        """Seconds since the epoch started."""
        return time.monotonic() - self.epoch_start

    def start_epoch(self) -> None:
        self.epoch_start = time.monotonic()

    def checkpoint_due(self, minutes: float) -> bool:
        """Whether ``minutes`` have passed since the last checkpoint (:meth:`checkpointed`)."""
        return time.monotonic() - self.last_checkpoint >= minutes * 60.0

    def checkpointed(self) -> None:
        self.last_checkpoint = time.monotonic()


def _fmt(value) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


class EpochLog:
    """``training_log.csv``, one row per epoch, appended and flushed.

    Args:
        path: the file; rewritten with its rows up to ``keep_until_epoch`` (a resumed run), or
            with the header alone (None).
        enabled: False on a process other than rank 0: writes nothing.
    """

    def __init__(self, path: Path, keep_until_epoch: int | None, enabled: bool = True):
        self.path, self.enabled = path, enabled
        if not enabled:
            return
        rows: list[dict] = []
        if keep_until_epoch is not None and path.is_file():
            with path.open(newline="", encoding="utf-8") as f:
                rows = [r for r in csv.DictReader(f) if int(r["epoch"]) <= keep_until_epoch]
        with atomic_output(path) as tmp:
            with tmp.open("w", newline="", encoding="utf-8") as f:
                writer = csv.DictWriter(f, LOG_COLUMNS)
                writer.writeheader()
                writer.writerows(rows)

    def write(self, row: dict[str, Any]) -> None:
        if not self.enabled:
            return
        with self.path.open("a", newline="", encoding="utf-8") as f:
            csv.DictWriter(f, LOG_COLUMNS).writerow({k: _fmt(row.get(k)) for k in LOG_COLUMNS})


def progress_note(info: dict[str, Any]) -> str:
    """The progress note of a step: epoch, loss, and the last validation's medians."""
    note = f"epoch {info.get('epoch', '?')}"
    if "loss" in info:
        note += f", loss {info['loss']:.3g}"
    if "val_RTE_mm" in info:
        note += f", validation {info['val_RTE_mm']:.1f} mm / {info['val_RRE_deg']:.1f} deg"
    return note
