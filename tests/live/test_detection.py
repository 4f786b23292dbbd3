"""Bone detection off the update loop (comreg_core.live.detection): real spawned workers give the
detections of the update loop's own function, bit for bit; a worker that dies is let go with a
note, and its frame is detected here."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.detection import DetectionPool, default_workers
from comreg_core.live.points import detect_frame
from comreg_core.live.stream import Frame
from tests.helpers import FIBULA_DIR

#: Seconds a test waits for the workers at most (they start in a few seconds).
WAIT_S = 90.0


@pytest.fixture(scope="module")
def frames(shared_data):
    sweep = read_tracked_sweep(FIBULA_DIR)
    return [Frame(k, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i],
                  float(sweep.timestamps[i]), 100.0 + k) for k, i in enumerate(range(30, 36))]


def _collect(pool, n):
    found, end = [], time.monotonic() + WAIT_S
    while len(found) < n and time.monotonic() < end:
        found += pool.collect(0.05)
    return found


def test_workers_find_what_the_update_loop_would(frames):
    assert 1 <= default_workers() <= 4
    assert [default_workers(cores) for cores in (1, 2, 3, 4, 5, 16)] == [1, 2, 2, 3, 4, 4]
    with DetectionPool(2) as pool:
        assert pool.wait_ready(WAIT_S) and pool.workers == 2
        found = []
        for frame in frames:
            while not pool.free():
                found += pool.collect(0.05)
            pool.submit(frame)
        found += _collect(pool, len(frames) - len(found))
        assert pool.busy == 0 and pool.notes == []
    assert sorted(d.index for d in found) == list(range(len(frames)))
    for detection in found:
        here = detect_frame(frames[detection.index])
        assert np.array_equal(detection.points, here.points)  # the same bits
        assert np.array_equal(detection.scores, here.scores)
        assert len(detection.points) > 20 and detection.detect_s > 0
        assert detection.received_s == 100.0 + detection.index
        assert np.array_equal(detection.T_ref_image, frames[detection.index].T_ref_image)
    with DetectionPool(0) as inline:  # no worker: detected in the calling thread
        assert inline.free() and inline.workers == 0
        inline.submit(frames[0])
        (one,) = inline.collect()
        assert np.array_equal(one.points, detect_frame(frames[0]).points)


def test_a_worker_that_dies_is_let_go_and_its_frame_detected_here(frames):
    with DetectionPool(1) as pool:
        assert pool.wait_ready(WAIT_S)
        os.kill(pool._workers[0].process.pid, signal.SIGKILL)
        pool._workers[0].process.join(10)
        pool.submit(frames[1])  # a broken pipe now, or the end of the stream when collecting
        found = _collect(pool, 1)
        assert pool.workers == 0 and pool.free()
        assert [d.index for d in found] == [1]
        assert np.array_equal(found[0].points, detect_frame(frames[1]).points)
        assert len(pool.notes) == 1 and "detection runs in the update process" in pool.notes[0]
        pool.submit(frames[2])  # from now on here
        assert [d.index for d in pool.collect()] == [2]


_FAULTS_SCRIPT = """
import resource, sys
import numpy as np
from comreg_core.live.background import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else None
sizes = np.random.default_rng(0).integers(25_000, 190_000, size=12)
for round in range(21):  # a detection's arrays: a dozen of 0.2-1.5 MB alive at once, then freed
    if round == 1:  # the first round touches the memory the others may reuse
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    arrays = [np.ones(int(n)) for n in sizes]
    del arrays
print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def test_workers_reuse_the_memory_they_free():
    """With :func:`keep_freed_memory`, arrays made and freed again and again are made in memory
    already touched: (nearly) no page faults, against one per 4 KiB page without it (the
    kernel's count, ``ru_minflt``, in a fresh process each)."""
    import subprocess
    import sys

    def faults(mode):
        out = subprocess.run([sys.executable, "-c", _FAULTS_SCRIPT, mode], capture_output=True,
                             text=True, timeout=120, check=True).stdout.split()
        return out[0], int(out[1])

    kept, with_it = faults("keep")
    if kept != "True":
        pytest.skip("not glibc: mallopt is not there")
    _, without = faults("default")
    pages = 20 * 12 * 25_000 * 8 // 4096  # the least that 20 rounds of fresh arrays touch
    assert without > pages
    assert with_it < 0.1 * pages
