"""A live update's record (:class:`LiveUpdate`: what was registered and judged, and what to
tell the user), ``updates.csv``, one row per update (:class:`UpdatesLog`,
:func:`read_updates`), and ``frames.csv``, one row per frame (:func:`write_frames_csv`)."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: ``updates.csv``'s columns.
UPDATE_COLUMNS = ("time_s", "frames_received", "frames_used", "covered_mm", "verdict",
                  "p_correct", "bound_mm", "latency_s", "update_s", "frame_age_s", "skipped_no_new_bone",
                  "dropped_lag", "dropped_no_pose", "centroid_x", "centroid_y", "centroid_z",
                  *(f"T_ct_us_{r}{c}" for r in range(3) for c in range(4)), "mode", "reasons")
#: ``updates.csv``'s columns that hold text (the others are numbers).
TEXT_COLUMNS = ("verdict", "mode", "reasons")


@dataclass
class LiveUpdate:
    """One update: what was registered and judged, and what to tell the user.

    Attributes:
        time_s: since the session started (s). frames_received, frames_used: so far.
        n_points: bone points registered. covered_mm: bone covered along the CT's long axis.
        verdict: "ok"/"check"; reasons: why CHECK. p_correct: None without a calibration.
        confidence: the registration's (the pose search's). advice: "enough" or where to scan.
        T_ct_us: ``(4, 4)`` tracker reference -> CT (the CT's space, mm).
        centroid: ``(3,)`` of the points (tracker frame, mm).
        mode: "full", "warm" or "warm+full" (a warm result the full search replaced; with a
            background full search: warm from the full search's result that just came).
        register_s: the update's time (s): detection, registration, verdict.
        waiting: frames left in the backlog for later updates (the loop is lagging).
        newest_s: arrival (``time.monotonic()``) of the update's newest input: the newest frame
            registered, or for an update without new frames (a background full search's
            answer alone) the answer; latency_s: from it to the update being
            sent (set by whoever sends it).
        searching: a full search runs in the background (its answer comes with a later update).
        frame_age_s: the age of the oldest frame this update took (s, from its arrival).
        skipped, dropped_lag, dropped_no_pose: frames so far skipped (no new bone: not a loss),
            dropped while lagging, and images without a usable pose (set by whoever receives
            them).
        bound_mm: the pose's 95 % bound at the bone (mm); weakest: its weakest directions in
            words (the one judge's uncertainty; None / "" when not judged).
    """

    time_s: float
    frames_received: int
    frames_used: int
    n_points: int
    covered_mm: float
    verdict: str
    reasons: list[str]
    p_correct: float | None
    confidence: float | None
    advice: str
    T_ct_us: np.ndarray
    centroid: np.ndarray
    mode: str
    register_s: float
    waiting: int
    newest_s: float
    latency_s: float = float("nan")
    searching: bool = False
    frame_age_s: float = float("nan")
    skipped: int = 0
    dropped_lag: int = 0
    dropped_no_pose: int = 0
    bound_mm: float | None = None
    weakest: str = ""

    def csv_row(self) -> list:
        """The ``updates.csv`` row (:data:`UPDATE_COLUMNS`)."""
        p = "" if self.p_correct is None else f"{self.p_correct:.4f}"
        bound = "" if self.bound_mm is None else f"{self.bound_mm:.2f}"
        return [f"{self.time_s:.3f}", self.frames_received, self.frames_used,
                f"{self.covered_mm:.1f}", self.verdict, p, bound, f"{self.latency_s:.3f}",
                f"{self.register_s:.3f}", f"{self.frame_age_s:.3f}", self.skipped, self.dropped_lag, self.dropped_no_pose,
                *(f"{v:.4f}" for v in self.centroid),
                *(repr(float(v)) for v in self.T_ct_us[:3].reshape(-1)), self.mode,
                " | ".join(self.reasons)]

    def status_line(self) -> str:
        """One line for the terminal."""
        p = "n/a" if self.p_correct is None else f"{self.p_correct:.2f}"
        lag = f"; LAGGING: {self.waiting} frames waiting" if self.waiting else ""
        late = f"; LATE by {self.latency_s:.1f} s" if self.latency_s > 1.0 else ""
        lost = "".join(f", {n} {why}" for n, why in (
            (self.dropped_lag, "dropped (lag)"), (self.dropped_no_pose, "without a pose")) if n)
        return (f"[{self.time_s:7.1f} s] frames {self.frames_used}/{self.frames_received}, "
                f"{self.n_points} points, {self.covered_mm:.0f} mm covered | {self.mode} "
                f"{self.register_s:.2f} s{', full search running' if self.searching else ''}, "
                f"latency {self.latency_s:.2f} s | "
                f"{self.verdict.upper()} p_correct {p}"
                + ("" if self.bound_mm is None else f", within {self.bound_mm:.1f} mm")
                + f" | {self.advice} | "
                f"{self.skipped} skipped (no new bone){lost}{lag}{late}")

    def message_text(self) -> str:
        """The STRING sent back: JSON with ``verdict``, ``p_correct``, ``bound_mm``,
        ``weakest``, ``covered_mm``, ``advice``, ``frames_used``, ``frames_received``,
        ``reasons``."""
        return json.dumps({"verdict": self.verdict, "p_correct": self.p_correct,
                           "bound_mm": self.bound_mm, "weakest": self.weakest,
                           "covered_mm": round(self.covered_mm, 1), "advice": self.advice,
                           "frames_used": self.frames_used,
                           "frames_received": self.frames_received, "reasons": self.reasons})


class UpdatesLog:
    """``updates.csv``: the header, then one row per update (:data:`UPDATE_COLUMNS`), each
    flushed as it is written, so the file is complete up to the last update at any moment."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(UPDATE_COLUMNS)
        self._file.flush()

    def write(self, update: LiveUpdate) -> None:
        self._writer.writerow(update.csv_row())
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()


def read_updates(path: str | Path) -> list[dict]:
    """The rows of an ``updates.csv`` as dicts of floats (:data:`TEXT_COLUMNS` strings; the
    ``reasons`` joined by " | "), an empty number None."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            rows.append({k: (v if k in TEXT_COLUMNS else (None if v == "" else float(v)))
                         for k, v in row.items()})
    return rows


def row_transform(row: dict) -> np.ndarray:
    """``T_ct_us`` ``(4, 4)`` of an ``updates.csv`` row (:func:`read_updates`)."""
    T = np.eye(4)
    T[:3] = np.array([row[f"T_ct_us_{r}{c}"] for r in range(3) for c in range(4)]).reshape(3, 4)
    return T


#: ``frames.csv``'s columns.
FRAME_COLUMNS = ("index", "timestamp_s", "received_s", "fate", "used_s", "age_s", "raw_points",
                 *(f"T_ref_image_{r}{c}" for r in range(3) for c in range(4)))


def write_frames_csv(fates: list, records: list, started_s: float, path: str | Path) -> None:
    """``frames.csv``: one row per frame that came with a usable pose, in stream order
    (:data:`FRAME_COLUMNS`), from the gate's ``fates``
    (:class:`~comreg_core.live.intake.FrameFate`) and the ``records`` of the frames used
    (:class:`~comreg_core.live.points.FrameRecord`): its time stamp, arrival (s since
    ``started_s``), fate (``used``, ``skipped``: no new bone, ``lag``: dropped while lagging),
    when an update took it and how old it was then (empty: not used, or used at the stop), the
    raw bone points found (empty: not detected) and its pose ``T_ref_image`` (top three
    rows)."""
    found = {rec.index: rec.raw_points for rec in records}
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(FRAME_COLUMNS)
        for fate in sorted(fates, key=lambda x: x.index):
            used = fate.fate == "used" and np.isfinite(fate.at_s)
            writer.writerow([fate.index, repr(fate.timestamp),
                             f"{fate.received_s - started_s:.4f}", fate.fate,
                             f"{fate.at_s - started_s:.4f}" if used else "",
                             f"{fate.at_s - fate.received_s:.4f}" if used else "",
                             found.get(fate.index, ""),
                             *(repr(float(v)) for v in fate.T_ref_image[:3].reshape(-1))])
