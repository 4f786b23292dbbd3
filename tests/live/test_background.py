"""The live full search in a second process (comreg_core.live.background): a real spawned
worker gives the result the session's own process gives for the same points; a session using it
registers warm every update (from the worker's first full search), adopts each answer in a
later update, and turns OK only there; a worker that cannot start is let go with a note and the session searches itself."""

from __future__ import annotations

import re
import signal
import time

import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.background import (FULL_SEARCH_NICENESS, FullSearchJob, FullSearchWorker,
                                         RegistrarRecipe, one_thread)
from comreg_core.live.session import LiveSession
from comreg_core.live.stream import Frame
from tests.helpers import FIBULA_STL, assert_close
from tests.live.conftest import cut_sweep

#: Seconds a test waits for the worker at most (it starts in ~5 s; a search takes ~1 s).
WAIT_S = 90.0


def _wait(condition, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < deadline, f"the worker did not {what} in {WAIT_S:g} s"
        time.sleep(0.02)


@pytest.fixture(scope="module")
def sweep(shared_data, tmp_path_factory):
    return read_tracked_sweep(cut_sweep(tmp_path_factory.mktemp("sweep_b"), 45, 30))


@pytest.fixture(scope="module")
def worker(shared_data):
    with FullSearchWorker(RegistrarRecipe(str(FIBULA_STL))) as running:
        assert running.wait_ready(WAIT_S), running.failed
        yield running


def _frames(sweep, indices):
    return [Frame(i, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i],
                  float(sweep.timestamps[i]), 0.0) for i in indices]


def test_the_ready_worker_yields_the_processor_to_detection_and_updates(worker):
    """Once ready, the worker runs FULL_SEARCH_NICENESS nicer than this process (capped at
    the system's 19): when cores are short, detection and the update loop go first."""
    import os

    mine = os.getpriority(os.PRIO_PROCESS, 0)
    theirs = os.getpriority(os.PRIO_PROCESS, worker._process.pid)
    assert theirs == min(19, mine + FULL_SEARCH_NICENESS), (mine, theirs)


def test_one_thread_limits_numba_torch_and_pykdtree_openmp_and_restores_them():
    """The update loop's threads (one_thread): numba, torch and every loaded OpenMP library
    (pykdtree's own among them) at 1 inside, the counts before after; closest points in it
    (the serial kernel, pykdtree alone) equal those outside, bit for bit."""
    import numba
    import numpy as np
    import torch
    from threadpoolctl import threadpool_info

    from comreg_core.registration.geometry.surface import CTSurface

    surface = CTSurface(FIBULA_STL)
    points = surface.samples(500)[0] + np.random.default_rng(3).normal(size=(500, 3))
    outside = surface.closest(points, 5.0)
    before = (numba.get_num_threads(), torch.get_num_threads(),
              [i["num_threads"] for i in threadpool_info() if i["user_api"] == "openmp"])
    with one_thread():
        openmp = [i for i in threadpool_info() if i["user_api"] == "openmp"]
        assert any("pykdtree" in i["filepath"] for i in openmp), openmp
        assert {i["num_threads"] for i in openmp} == {1}
        assert numba.get_num_threads() == torch.get_num_threads() == 1
        inside = surface.closest(points, 5.0)
    after = (numba.get_num_threads(), torch.get_num_threads(),
             [i["num_threads"] for i in threadpool_info() if i["user_api"] == "openmp"])
    assert after == before
    assert np.isfinite(inside[2]).sum() > 400
    for a, b in zip(outside, inside):
        np.testing.assert_array_equal(a, b)


def test_the_worker_finds_what_the_session_would(worker, sweep, search_registrar):
    session = LiveSession(search_registrar)
    for frame in _frames(sweep, range(12)):
        session.points.add(frame)
    cloud = session.points.cloud()
    origins = session.points.beam_origins(cloud)
    worker.submit(FullSearchJob(7, cloud.points, origins, 3, halves=True))
    answers = []
    _wait(lambda: answers.append(worker.poll()) or answers[-1] is not None, "answer")
    done = answers[-1]
    assert done.job == 7 and done.error is None and worker.busy is None
    here = search_registrar.register(cloud.points, seed=3, beam_origins=origins,
                                     residuals=False)
    assert_close(done.result.T_ct_us, here.T_ct_us, atol=1e-9)
    assert done.result.confidence == pytest.approx(here.confidence, abs=1e-9)
    assert done.halves_deg is not None and done.halves_deg >= 0.0
    with pytest.raises(Exception, match="not free"):  # one job at a time
        worker.submit(FullSearchJob(8, cloud.points, origins, 3, halves=False))
        worker.submit(FullSearchJob(9, cloud.points, origins, 3, halves=False))
    _wait(lambda: worker.poll() is not None, "answer")


def test_a_session_with_the_worker_is_warm_and_adopts_full_searches(worker, sweep,
                                                                   search_registrar):
    session = LiveSession(search_registrar, worker=worker)
    session.first_search_beside = True  # as comreg live
    updates = []
    for start in range(0, 30, 2):
        update = session.update(_frames(sweep, range(start, start + 2)))
        if update is not None:
            updates.append(update)
        # the next update sees the answer: wait for it, so the order is the same on any machine
        _wait(lambda: not session.searching or worker.wait(0.05), "answer")
    modes = [u.mode for u in updates]
    # the first full search too runs in the worker: no update waits for a search
    assert modes[0] == "warm+full" and "full" not in modes
    adopted = [k for k, mode in enumerate(modes) if mode == "warm+full"]
    assert len(adopted) >= 3
    for k in adopted[1:]:  # each later answer asked for by the update before
        assert updates[k - 1].searching
    for before, after in zip(updates, updates[1:]):  # OK comes only with a full search
        if after.verdict == "ok" and before.verdict != "ok":
            assert after.mode == "warm+full"
    confirming = [u for u in updates if any("is confirming" in r for r in u.reasons)]
    assert all(u.verdict == "check" and u.mode == "warm" for u in confirming)
    assert session.take_notes() == []
    # the end of a stream: the last answer comes with an update without new frames, whose
    # latency runs from the answer (its newest input), not from the last frame
    assert session.answer_waiting()
    before = time.monotonic()
    final = session.update()
    assert final.mode == "warm+full" and final.frames_used == updates[-1].frames_used
    assert before <= final.newest_s <= time.monotonic()
    assert updates[-1].newest_s < before


def test_a_worker_that_cannot_start_is_let_go(shared_data, tmp_path, search_registrar,
                                              sweep):
    ours = signal.getsignal(signal.SIGINT)  # SIG_IGN when the test run was started with "&"
    broken = FullSearchWorker(RegistrarRecipe(str(tmp_path / "missing.stl")))
    try:
        # from its start (still importing): Ctrl-C, which a terminal sends to the whole
        # process group, ignored (live alone handles it), and one thread
        pid = broken._process.pid
        _wait(lambda: b"multiprocessing" in open(f"/proc/{pid}/cmdline", "rb").read(),
              "start Python")  # exec'd: what it has now, it inherited
        ignored = int(re.search(r"SigIgn:\s*([0-9a-f]+)",
                                open(f"/proc/{pid}/status").read()).group(1), 16)
        assert ignored & (1 << (signal.SIGINT - 1))
        assert b"NUMBA_NUM_THREADS=1" in open(f"/proc/{pid}/environ", "rb").read().split(b"\0")
        assert signal.getsignal(signal.SIGINT) == ours  # ours is back
        _wait(lambda: broken.poll() is None and broken.failed is not None, "fail")
        assert "could not start" in broken.failed and "missing.stl" in broken.failed
        session = LiveSession(search_registrar, worker=broken)
        first = session.update(_frames(sweep, range(8)))
        second = session.update(_frames(sweep, range(8, 20)))
        assert first.mode == "full" and not first.searching and not second.searching
        notes = session.take_notes()
        assert len(notes) == 1 and "run in the update loop" in notes[0]
        assert session.worker is None
    finally:
        broken.close()
    assert not broken._process.is_alive()
