"""The one progress-callback type of the library.

Long-running functions take ``progress: Progress | None`` and call it as
``progress(done, total, note)``: ``done`` of ``total`` units of work finished (frames, sweeps,
trials, training steps, screenshots, thousandths of a stage list), ``note`` a short word on what
is running now (may be empty). The CLI turns it into a progress bar, the plugin into its
progress display; library code never prints.
"""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    """``progress(done, total, note="")``; see the module docstring."""

    def __call__(self, done: int, total: int, note: str = "") -> None: ...


def silent(done: int, total: int, note: str = "") -> None:
    """A :class:`Progress` that ignores every report (the default when none is given)."""
