"""``python -m tests.training.fixed_fps_cli ARGS``: the ``comreg`` command with every farthest-
point sampling started at point 0, as in eval mode, also in training.

In training the network starts each FPS at a random point drawn for the whole batch at once, so
a batch split over two processes draws other starts than one process does: a legitimate
difference that would hide everything else when comparing two processes with one. With the
starts fixed, one process with batch 4 and two with batch 2 each must agree up to float
rounding. :func:`fix_fps_starts` is the same change for a test's own process.
"""

from __future__ import annotations

from comreg_core.model import adapointr, ops

_random_start_fps = ops.furthest_point_sample


def _fps_from_point_0(points, n, start_index=0, backend="auto"):
    return _random_start_fps(points, n, 0 if start_index is None else start_index, backend)


def fix_fps_starts(monkeypatch=None) -> None:
    """Make every FPS start at point 0 (with pytest's ``monkeypatch``: undone after the test)."""
    for module in (ops, adapointr):
        if monkeypatch is None:
            module.furthest_point_sample = _fps_from_point_0
        else:
            monkeypatch.setattr(module, "furthest_point_sample", _fps_from_point_0)


if __name__ == "__main__":
    fix_fps_starts()
    from comreg_core.cli import main

    main()
