"""Pretraining on several processes: ``torchrun`` + ``DistributedDataParallel`` (DDP).

``comreg pretrain`` needs no option for it: started by ``torchrun`` (which sets ``RANK``,
``WORLD_SIZE`` and ``LOCAL_RANK``), :func:`~comreg_core.training.trainer.pretrain` runs one
process per device and this module supplies the parts:

* :class:`World`: this process's rank among ``size`` processes, read from torchrun's
  environment (a plain run is ``World()``: rank 0 of 1, no ``torch.distributed``).
* :func:`start` / :func:`stop`: the process group (NCCL on CUDA, gloo on the CPU), each process
  on the GPU ``cuda:LOCAL_RANK``; ``SIGTERM`` (torchrun stopping the survivors when a process
  failed) becomes :class:`JobStoppedError`, so a stopped process exits with one line and leaves
  no half-written file.
* :func:`wrap_model`: the DDP wrapper. The network's normalisation layers (GroupNorm,
  LayerNorm) use per-sample statistics and keep no running buffers, so nothing needs
  synchronising (no SyncBatchNorm; :func:`wrap_model` refuses batch-statistics layers). AdaPoinTr's
  query-ranking MLP only orders queries (argsort) and never receives a gradient, in every
  step, and the data-dependent part of a step (ICP runs only on the samples inside the fine-loss
  gate) has no weights, so every process uses the same parameters in every step: DDP is told
  the graph is static instead of searching for unused parameters each step.
* :meth:`World.mean` and :meth:`World.main_decides`: the two collectives of a training step,
  the loss terms averaged over processes (logged, and the adaptive loss weight computed from
  the global batch), and rank 0's stop decision (time budget) broadcast, so every process takes
  the same branch and runs the same backward.

What the processes share (the trainer's rules): ``training.batch_size`` is the global batch of
one step, split evenly (it must be a multiple of the process count); an epoch is
``samples_per_epoch`` samples at any process count; DDP averages the gradients of the per-process
batch means, which equals the gradient of the global batch mean. The learning rates are those
of the global batch, so the world size changes the speed and never the optimisation. Rank 0
alone validates (on the unwrapped network, the same figures as one process; the others wait at
the next step) and writes the run folder. A process restarted by torchrun (``--max-restarts``)
resumes its run from the checkpoint.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Mapping

import torch

from comreg_core.errors import ComRegError

log = logging.getLogger(__name__)

#: torchrun's environment variables that mark a process it started.
LAUNCH_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK")


class DistributedError(ComRegError):
    """A multi-process launch that cannot work (torchrun's environment, GPUs, batch split), or
    a process of the job that stopped."""


class JobStoppedError(DistributedError):
    """The job stops: torchrun stopped this process (``SIGTERM``) or another process is lost."""


@dataclass(frozen=True)
class World:
    """This process's place among the processes training together.

    Attributes:
        rank: 0 ... ``size - 1``; rank 0 alone writes the run folder, logs and progress.
        size: number of processes (torchrun's ``WORLD_SIZE``).
        local_rank: rank on this machine (the GPU index on CUDA).
        launched: started by torchrun (``torch.distributed`` is used); False for a plain run.
        restart: torchrun's restart count (``TORCHELASTIC_RESTART_COUNT``; 0 on the first try).
    """

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    launched: bool = False
    restart: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_environment(cls, env: Mapping[str, str] | None = None) -> World:
        """The world torchrun describes in ``env`` (default ``os.environ``); ``World()`` when
        none of its variables is set.

        Raises:
            DistributedError: some but not all of them set, or values out of range.
        """
        env = os.environ if env is None else env
        present = [name for name in LAUNCH_VARIABLES if name in env]
        if not present:
            return cls()
        if len(present) < len(LAUNCH_VARIABLES):
            missing = ", ".join(n for n in LAUNCH_VARIABLES if n not in env)
            raise DistributedError(f"The environment sets {', '.join(present)} but not {missing}: "
                                   "this process was not started by torchrun.",
                                   "Start several processes with 'torchrun --nproc_per_node N "
                                   "-m comreg_core.cli pretrain ...', or unset these variables "
                                   "for a single process.")
        try:
            rank, size, local = (int(env[name]) for name in LAUNCH_VARIABLES)
            restart = int(env.get("TORCHELASTIC_RESTART_COUNT", "0"))
        except ValueError:
            raise DistributedError("torchrun's RANK, WORLD_SIZE or LOCAL_RANK is not an integer "
                                   f"({', '.join(f'{n}={env[n]!r}' for n in LAUNCH_VARIABLES)}).",
                                   "Launch with torchrun, which sets them.") from None
        if size < 1 or not 0 <= rank < size or local < 0 or restart < 0:
            raise DistributedError(f"torchrun's environment is inconsistent (RANK={rank}, "
                                   f"WORLD_SIZE={size}, LOCAL_RANK={local}).",
                                   "Launch with torchrun, which sets them.")
        return cls(rank, size, local, True, restart)

    def check_batch(self, batch_size: int) -> None:
        """Raise :class:`DistributedError` unless ``batch_size`` splits evenly over the
        processes."""
        if batch_size % self.size:
            raise DistributedError(
                f"training.batch_size {batch_size} (the global batch of a step) does not split "
                f"evenly over {self.size} processes.",
                f"Start a number of processes that divides {batch_size}, or set "
                f"training.batch_size to a multiple of {self.size} with --config (then scale "
                "the learning rates yourself; see the README).")

    def device(self, device: torch.device) -> torch.device:
        """This process's device: ``cuda:LOCAL_RANK`` when training on CUDA, else ``device``.

        Raises:
            DistributedError: fewer GPUs on this machine than processes.
        """
        if not self.launched or device.type != "cuda":
            return device
        count = torch.cuda.device_count()
        if self.local_rank >= count:
            raise DistributedError(f"Process {self.local_rank} on this machine needs GPU "
                                   f"{self.local_rank}, but it has {count}.",
                                   f"Start at most {count} processes per machine "
                                   "(torchrun --nproc_per_node), or train with --device cpu.")
        return torch.device("cuda", self.local_rank)

    def mean(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` averaged over the processes (element-wise; detached). A plain run returns
        ``values`` (detached) unchanged."""
        values = values.detach()
        if not self.launched:
            return values
        total = values.clone()
        _collective(torch.distributed.all_reduce, total)
        return total / self.size

    def main_decides(self, flag: bool, device: torch.device) -> bool:
        """Rank 0's ``flag``, the same on every process (the others' ``flag`` is ignored)."""
        if not self.launched:
            return flag
        value = torch.tensor([int(flag)], dtype=torch.int32, device=device)
        _collective(torch.distributed.broadcast, value, src=0)
        return bool(value.item())


def _collective(operation, *args, **kwargs) -> None:
    with peer_failures_reported():
        operation(*args, **kwargs)


def is_communication_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is the communication library's report of a lost process: a
    ``torch.distributed.DistError``, or a ``RuntimeError`` from gloo or NCCL (DDP's gradient
    all-reduce in ``backward`` raises gloo's as a plain ``RuntimeError``)."""
    if isinstance(exc, getattr(torch.distributed, "DistError", ())):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and ("gloo" in text or "NCCL" in text)


@contextmanager
def peer_failures_reported():
    """Turn a lost process of the job (:func:`is_communication_failure`) into
    :class:`JobStoppedError`: a one-line error, not a bug report."""
    try:
        yield
    except RuntimeError as exc:
        if not is_communication_failure(exc):
            raise
        _ignore_sigterm()  # torchrun's SIGTERM must not cut the error line short
        text = str(exc).strip().splitlines()
        first = re.sub(r"^\[[^\]]*\]\s*", "", text[0] if text else type(exc).__name__)
        first = first.split(". ")[0][:200]  # gloo: "[file:line] Connection closed by peer ..."
        raise JobStoppedError(f"The processes of this torchrun job lost contact ({first}): "
                              "another process stopped or cannot be reached.",
                              "The run folder keeps its last checkpoint: run the same command "
                              "with --resume.") from exc


_previous_sigterm: list = []


def _ignore_sigterm() -> None:
    """Ignore further SIGTERMs: the process is already stopping with its error."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _stopped_by_signal(signum, frame) -> None:
    _ignore_sigterm()
    raise JobStoppedError("torchrun stopped this process (another process of the job failed, or "
                          "the job was cancelled).", "The run folder keeps its last checkpoint: "
                          "run the same command with --resume.")


def start(world: World, device: torch.device) -> None:
    """Join the job's process group (NCCL on CUDA, gloo otherwise) and wait for every process;
    a plain run does nothing. On CUDA, ``device`` (from :meth:`World.device`) becomes current."""
    if not world.launched:
        return
    import torch.distributed as dist

    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if threading.current_thread() is threading.main_thread():
        _previous_sigterm.append(signal.signal(signal.SIGTERM, _stopped_by_signal))
    dist.init_process_group(backend, rank=world.rank, world_size=world.size)
    world.mean(torch.zeros(1, device=device))  # every process has joined
    log.info("Process %d of %d (local %d) on %s, backend %s", world.rank, world.size,
             world.local_rank, device, backend)


def stop(world: World) -> None:
    """Leave the process group and restore the ``SIGTERM`` handler, unless the job is stopping
    (then SIGTERM stays ignored until the process has reported its error and exited)."""
    if not world.launched:
        return
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()
    if _previous_sigterm and threading.current_thread() is threading.main_thread():
        previous = _previous_sigterm.pop()
        if signal.getsignal(signal.SIGTERM) is _stopped_by_signal:
            signal.signal(signal.SIGTERM, previous)


#: Normalisation layers whose batch statistics would differ per process under DDP.
_BATCH_STATISTICS = (torch.nn.modules.batchnorm._BatchNorm,)


def wrap_model(model: torch.nn.Module, world: World, device: torch.device) -> torch.nn.Module:
    """``model`` in ``DistributedDataParallel`` when launched (else ``model`` itself). DDP copies
    rank 0's weights to every process here and averages the gradients in ``backward``."""
    if not world.launched:
        return model
    batch_norms = [name for name, m in model.named_modules() if isinstance(m, _BATCH_STATISTICS)]
    if batch_norms:  # a change of the network would have to convert them to SyncBatchNorm
        raise ValueError(f"batch-statistics layers under DDP: {batch_norms}")
    from torch.nn.parallel import DistributedDataParallel

    return DistributedDataParallel(
        model, device_ids=[device.index] if device.type == "cuda" else None,
        static_graph=True)  # the same parameters are used (and the same unused) in every step
