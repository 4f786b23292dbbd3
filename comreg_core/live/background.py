"""The live full search in a second process (:class:`FullSearchWorker`), so that warm updates go
on while it runs.

Why a process: a full search takes 0.4-1 s on 2 CPU cores, and the frames that arrive while it
runs wait for it. A thread does not help: Python runs one thread at a time, and a warm update
beside a full search in a thread took 0.25 s instead of 0.11 s. In a second process, each
process on one thread, a warm update took 0.15 s beside it (0.13 s alone) and the full search
~1.1 s (``docs/live.md``).

The worker builds its own :class:`~comreg_core.register.Registrar` from the same recipe (the
CT mesh, the network's run or none, the device: :func:`build_registrar`) and registers the jobs
it is given, one at a time, as :meth:`LiveSession <comreg_core.live.session.LiveSession>` would
in its own process (the same seed, prior and points: the same result, thread counts do not
change it). It is started with ``spawn`` (a forked copy of a process whose numba and torch
thread pools run can hang) and each process runs its kernels on one thread while it lives.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from comreg_core.errors import ComRegError

log = logging.getLogger(__name__)

#: Environment variables that set a library's thread count at its import.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "NUMBA_NUM_THREADS")
#: Seconds ``comreg live`` waits for the worker to start (imports, the CT side, a first search).
WORKER_START_S = 60.0
#: Seconds :meth:`FullSearchWorker.close` waits for the worker to stop before killing it.
CLOSE_WAIT_S = 5.0
#: The full-search worker's niceness once it is ready (``os.nice``): when the processor is short
#: (a 30-40 frames/s stream on 2 cores), detection and the update loop go first and the full
#: search takes what they leave; on an idle core it runs as fast as before.
FULL_SEARCH_NICENESS = 10


@dataclass(frozen=True)
class RegistrarRecipe:
    """How to build the live session's registrar again in another process: ``ct_mesh`` (a
    path), ``run_dir`` (the network's run, None: the search alone), ``device`` (torch's)."""

    ct_mesh: str
    run_dir: str | None = None
    device: str = "auto"


def build_registrar(recipe: RegistrarRecipe):
    """The :class:`~comreg_core.register.Registrar` of ``recipe``."""
    from comreg_core.register import Registrar

    if recipe.run_dir is None:
        return Registrar.from_ct(recipe.ct_mesh)
    return Registrar.from_run(recipe.run_dir, recipe.device, ct_mesh=recipe.ct_mesh)


def warm_up_registrar(registrar, seed: int = 0):
    """Prepare ``registrar``'s CT side (search cloud, closest-point grid, the network's CT
    half) by registering a patch of the CT's own surface (the middle half of its length), so
    that its first live registration costs what later ones do. Returns ``(patch (n, 3),
    RegistrationResult)``."""
    from comreg_core.registration.geometry.surface import ct_length_mm

    target = registrar.search_target(registrar.search_config.target_points)
    samples, _ = registrar.surface.samples(2000)
    along = (samples - target.centre) @ target.axes[:, 0]
    patch = samples[np.abs(along - np.median(along)) < 0.25 * ct_length_mm(target)]
    return patch, registrar.register(patch, seed=seed)


@dataclass
class FullSearchJob:
    """A full search to run: ``points`` ``(N, 3)`` (tracker frame, mm), their beam ``origins``
    ``(N, 3)`` or None, the ``seed``; ``halves``: also measure
    :func:`~comreg_core.registration.search.polish.halves_disagreement_deg` of its pose."""

    job: int
    points: np.ndarray
    origins: np.ndarray | None
    seed: int
    halves: bool


@dataclass
class FullSearchDone:
    """A job's answer: the :class:`~comreg_core.registration.search.result.RegistrationResult` (None
    when it failed: ``error`` says why), the halves' disagreement (deg; None when not asked),
    and the ``seconds`` the worker took."""

    job: int
    result: object | None
    halves_deg: float | None
    seconds: float
    error: str | None = None


def _serve(recipe: RegistrarRecipe, prior, connection) -> None:
    """The worker process: build the registrar, say "ready", answer jobs until None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    keep_freed_memory()
    import torch

    from comreg_core.registration.search.polish import halves_disagreement_deg

    torch.set_num_threads(1)
    try:
        registrar = build_registrar(recipe)
        target = registrar.search_target(registrar.search_config.target_points)
        warm_up_registrar(registrar)
    except Exception as exc:  # the parent runs its full searches itself then
        connection.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    lower_priority(FULL_SEARCH_NICENESS)
    connection.send(("ready", None))
    while True:
        try:
            job = connection.recv()
        except EOFError:
            return
        if job is None:
            return
        start = time.perf_counter()
        try:
            result = registrar.register(job.points, seed=job.seed, beam_origins=job.origins,
                                        prior=prior, residuals=False)
            halves = None
            if job.halves:
                halves = halves_disagreement_deg(job.points, result.T_ct_us, target,
                                                 registrar.search_config,
                                                 origins=job.origins)
            done = FullSearchDone(job.job, result, halves, time.perf_counter() - start)
        except Exception as exc:
            done = FullSearchDone(job.job, None, None, time.perf_counter() - start,
                                  f"{type(exc).__name__}: {exc}")
        connection.send(done)


def lower_priority(niceness: int) -> None:
    """Raise this process's niceness by ``niceness`` (where the system allows it)."""
    try:
        os.nice(niceness)
    except (AttributeError, OSError):  # not on this system: the same results, later
        pass


#: ``mallopt`` settings of :func:`keep_freed_memory` (glibc's ``M_MMAP_THRESHOLD`` and
#: ``M_TRIM_THRESHOLD``): blocks up to 64 MiB come from the heap, and up to 256 MiB freed at
#: its top stay with the process.
_MALLOPT = ((-3, 64 << 20), (-1, 256 << 20))


def keep_freed_memory() -> bool:
    """Let this process reuse the memory it frees instead of giving it back to the system
    (glibc's ``mallopt``; elsewhere nothing changes: False). A detection maps a frame into a
    dozen arrays of 0.2-1.5 MB; by default glibc maps each anew, and the system zeroes every
    page at its first touch: ~1,800 page faults a fibula frame, a third of its time
    (``docs/live.md``). The results are the same bits either way."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError, TypeError):  # not glibc (Windows: no CDLL(None))
        return False
    return all(mallopt(option, value) == 1 for option, value in _MALLOPT)


@contextmanager
def child_environment():
    """While inside, the thread variables say 1 and (in the main thread) Ctrl-C is ignored: a
    process spawned then inherits both, so a Ctrl-C at the terminal, which reaches the whole
    process group, stops ``live`` alone, even while the worker is still starting."""
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    os.environ.update({name: "1" for name in THREAD_VARIABLES})
    main = threading.current_thread() is threading.main_thread()
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGINT, handler)
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextmanager
def one_thread():
    """While inside, this thread's numba kernels, torch and pykdtree's OpenMP queries run on one
    thread (the workers have the other core); the counts before come back on leaving. On 2
    cores shared with the detection workers, a second OpenMP thread only waited for a core at
    each query's barrier (at 40 frames/s: median latency 0.40-0.57 s with it, 0.25-0.37 s
    without; docs/live.md)."""
    import importlib

    import numba
    import torch
    from threadpoolctl import threadpool_limits

    importlib.import_module("pykdtree.kdtree")  # its OpenMP library loaded, so that it is limited

    numba_threads, torch_threads = numba.get_num_threads(), torch.get_num_threads()
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1, user_api="openmp"):
            yield
    finally:
        numba.set_num_threads(numba_threads)
        torch.set_num_threads(torch_threads)


class FullSearchWorker:
    """A second process that runs full searches for a live session (module docstring).

    Start it early (it needs a few seconds to build the registrar); :attr:`ready` says when it
    takes jobs. One job at a time: :meth:`submit`, then :meth:`poll` until its
    :class:`FullSearchDone` comes. :attr:`failed` says why it stopped working (then the
    session runs its full searches itself). A context manager: leaving it closes the worker.

    Args:
        recipe: the registrar to build (:class:`RegistrarRecipe`).
        prior: the session's :class:`~comreg_core.registration.search.priors.Prior` (in the
            registrar's space) or None.
    """

    def __init__(self, recipe: RegistrarRecipe, prior=None):
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(recipe, prior, child),
                                        name="comreg-full-search", daemon=True)
        with child_environment():
            self._process.start()
        child.close()
        self.ready = False
        self.failed: str | None = None
        self.busy: int | None = None  # the job running

    def __enter__(self) -> FullSearchWorker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def submit(self, job: FullSearchJob) -> None:
        """Hand ``job`` to the worker; it must be :attr:`ready` and not :attr:`busy`."""
        if not self.ready or self.busy is not None:
            raise ComRegError("The full-search worker is not free for a job.")
        self._connection.send(job)
        self.busy = job.job

    def poll(self) -> FullSearchDone | None:
        """The answer of the job running, when it has come (no waiting); also notices the
        worker becoming ready, failing or dying (:attr:`failed`)."""
        if self.failed is not None:
            return None
        try:
            while self._connection.poll():
                message = self._connection.recv()
                if isinstance(message, FullSearchDone):
                    self.busy = None
                    return message
                kind, text = message
                if kind == "ready":
                    self.ready = True
                else:
                    self._fail(f"the full-search worker could not start: {text}")
        except (EOFError, OSError) as exc:
            self._fail(f"the full-search worker stopped ({type(exc).__name__})")
            return None
        if not self._process.is_alive():
            self._fail(f"the full-search worker stopped (exit code {self._process.exitcode})")
        return None

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the worker to be :attr:`ready` (False: not yet, or it
        :attr:`failed`)."""
        deadline = time.monotonic() + timeout_s
        while not self.ready and self.failed is None and time.monotonic() < deadline:
            self._connection.poll(0.05)
            self.poll()
        return self.ready

    def wait(self, timeout_s: float) -> bool:
        """Whether a message (an answer) waits to be read by :meth:`poll`, waiting up to
        ``timeout_s`` for one; it is left for :meth:`poll`."""
        try:
            return self.failed is None and self._connection.poll(timeout_s)
        except (EOFError, OSError):
            return True  # poll() will tell

    def _fail(self, why: str) -> None:
        self.failed, self.ready, self.busy = why, False, None
        log.warning("%s", why)

    def close(self) -> None:
        """Stop the worker (it finishes nothing it was doing)."""
        close_process(self._process, self._connection)
        self.ready = False
        if self.failed is None:
            self.failed = "closed"


def close_process(process, connection) -> None:
    """Stop a worker ``process`` listening on ``connection``: None asks it to end, then it is
    terminated if it has not within 0.2 s (waited for up to :data:`CLOSE_WAIT_S`); the
    connection is closed."""
    if process.is_alive():
        try:
            connection.send(None)
        except (OSError, ValueError):  # a broken pipe, a closed connection
            pass
        process.join(0.2)
    if process.is_alive():
        process.terminate()
        process.join(CLOSE_WAIT_S)
    connection.close()
