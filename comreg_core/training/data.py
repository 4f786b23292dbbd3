"""Training data: an endless, deterministic stream of simulated samples for one CT.

Sample ``i`` of a run with seed ``s`` (paper, section 2):

1. ``S_hat``: a simulated US sweep of the CT bone (``simulate_sweep``; ``simulation.mode:
   uniform`` gives the paper's uniform-sampling ablation), in the CT frame, mm.
2. ``T`` (= ``T_us_ct``): a random rigid transform (``sample_initial_pose``, ``data.pose``
   ``"paper"`` by default), rotating about the CT bounding-box centre.
3. ``S^t = T . S_hat`` (the network's source) and ``T^t = T . T_ct`` (the CT cloud in the source
   pose: the completion's ground truth).
4. Both normalised with the CT's centre and scale (:class:`~comreg_core.model.Normalization`);
   the registration ground truth is ``T^-1`` in normalised units (source -> CT).

Random streams (``numpy.random.SeedSequence(seed, spawn_key=...)``), pairwise disjoint:

* training sample ``i``: ``sweep_rng(seed, i)`` (spawn key ``(i,)``); the sweep and the pose
  come from that one generator, so sample ``i`` is the same whatever the worker count and a
  resumed run continues the exact stream (sample index = samples already seen);
* validation sample ``j``: spawn key ``(VALIDATION_NAMESPACE, j)``;
* the CT cloud: spawn key ``(CT_CLOUD_NAMESPACE,)``;
* torch's global generator (the network's random farthest-point-sampling starts) is seeded
  before every training step from spawn key ``(STEP_NAMESPACE, i)``, ``i`` the first sample of
  the step's batch (of this process's part of it when training on several processes), so a
  resumed run needs no saved generator state and processes draw from disjoint streams;
* evaluation (``comreg_core.evaluation``) uses ``(EVALUATION_SEED_NAMESPACE, stream, index)``.

Samples are made in background worker processes (a ``torch.utils.data.DataLoader`` over an
:class:`IterableDataset` of whole batches), so the training step does not wait for the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from comreg_core.normalization import Normalization
from comreg_core.simulation.bone import BoneModel
from comreg_core.simulation.config import SimulationConfig
from comreg_core.simulation.poses import sample_initial_pose
from comreg_core.simulation.simulator import simulate_sweep, sweep_rng
from comreg_core.transforms import apply_transform, invert_rigid

#: First spawn-key word of the validation streams (ASCII "VALI").
VALIDATION_NAMESPACE = 0x56414C49
#: Spawn-key word of the CT cloud's stream (ASCII "CTPT").
CT_CLOUD_NAMESPACE = 0x43545054
#: First spawn-key word of the per-step torch seeds (ASCII "STEP").
STEP_NAMESPACE = 0x53544550


def validation_rng(seed: int, index: int) -> np.random.Generator:
    """Generator of held-out validation sample ``index`` (disjoint from training streams)."""
    return np.random.default_rng(np.random.SeedSequence(int(seed),
                                                        spawn_key=(VALIDATION_NAMESPACE, index)))


def step_torch_seed(seed: int, first_sample: int) -> int:
    """Seed of torch's global generator for the training step whose (part of the) batch starts
    at sample ``first_sample``: a 63-bit integer from spawn key ``(STEP_NAMESPACE, first_sample)``."""
    state = np.random.SeedSequence(int(seed), spawn_key=(STEP_NAMESPACE, int(first_sample)))
    return int(state.generate_state(1, np.uint64)[0] >> np.uint64(1))


def ct_cloud_rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(int(seed),
                                                        spawn_key=(CT_CLOUD_NAMESPACE,)))


@dataclass
class TrainingCT:
    """The CT a run trains for.

    Attributes:
        vertices, faces: the mesh (mm, the mesh file's space).
        points: ``(M, 3)`` float64 mm, the CT cloud ``T`` (area-uniform surface samples).
        normalization: CT bounding-box centre and largest extent.
    """

    vertices: np.ndarray
    faces: np.ndarray
    points: np.ndarray
    normalization: Normalization

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, n_points: int,
                  seed: int) -> TrainingCT:
        bone = BoneModel((vertices, faces))
        points, _ = bone.sample_surface(n_points, ct_cloud_rng(seed))
        return cls(bone.vertices, bone.faces, points,
                   Normalization.from_ct(bone.vertices[np.unique(bone.faces)]))


@dataclass
class Sample:
    """One training/validation sample (numpy; normalised units unless ``_mm``).

    Attributes:
        source: ``(n, 3)`` ``S^t`` normalised.
        gt_points: ``(M, 3)`` ``T^t`` (CT cloud moved by ``T``) normalised.
        gt_transform: ``(4, 4)`` ``T^-1`` normalised (source -> CT).
        T_us_ct_mm: ``(4, 4)`` the sampled ``T`` in mm.
    """

    source: np.ndarray
    gt_points: np.ndarray
    gt_transform: np.ndarray
    T_us_ct_mm: np.ndarray


def make_sample(bone: BoneModel, ct: TrainingCT, simulation: SimulationConfig, pose: str,
                rng: np.random.Generator) -> Sample:
    """Draw one sample from ``rng`` (sweep first, then pose)."""
    norm = ct.normalization
    sweep = simulate_sweep(bone, simulation, rng)
    T = sample_initial_pose(rng, pose, center=norm.center)
    source = norm.points_to_model(apply_transform(T, sweep.points))
    gt_points = norm.points_to_model(apply_transform(T, ct.points))
    gt_transform = invert_rigid(norm.transform_to_model(T))
    return Sample(source, gt_points, gt_transform, T)


def collate(samples: list[Sample], first_index: int) -> dict[str, torch.Tensor]:
    """Stack samples into a batch of float32 tensors."""
    f = torch.float32
    return {
        "index": torch.arange(first_index, first_index + len(samples), dtype=torch.int64),
        "source": torch.from_numpy(np.stack([s.source for s in samples])).to(f),
        "gt_points": torch.from_numpy(np.stack([s.gt_points for s in samples])).to(f),
        "gt_transform": torch.from_numpy(np.stack([s.gt_transform for s in samples])).to(f),
    }


class SampleStream(IterableDataset):
    """Endless batches of training samples, starting at sample ``start``.

    Global batch ``b`` holds samples ``start + b * batch_size + j``, ``j < batch_size``. Training
    on ``processes`` processes, process ``rank`` takes the contiguous part ``j = rank * n ...
    rank * n + n - 1`` of every global batch, ``n = batch_size // processes``: the processes
    draw disjoint samples, and together the same samples at any process count. With ``W``
    data workers, worker ``w`` makes batches ``b = w, w + W, ...`` and the DataLoader returns
    them in order, so the stream is identical for any worker count. Picklable (the ray-casting
    scene is built inside each worker).
    """

    def __init__(self, ct: TrainingCT, simulation: SimulationConfig, pose: str, seed: int,
                 batch_size: int, start: int = 0, rank: int = 0, processes: int = 1):
        super().__init__()
        if processes < 1 or not 0 <= rank < processes or batch_size % processes:
            raise ValueError(f"cannot split batches of {batch_size} over {processes} processes "
                             f"(rank {rank})")
        self.ct, self.simulation, self.pose = ct, simulation, pose
        self.seed, self.batch_size, self.start = int(seed), int(batch_size), int(start)
        self.rank, self.processes = int(rank), int(processes)

    def __iter__(self):
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        bone = BoneModel((self.ct.vertices, self.ct.faces))
        part = self.batch_size // self.processes
        b = worker
        while True:
            first = self.start + b * self.batch_size + self.rank * part
            samples = [make_sample(bone, self.ct, self.simulation, self.pose,
                                   sweep_rng(self.seed, first + j))
                       for j in range(part)]
            yield collate(samples, first)
            b += workers


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)


def sample_loader(stream: SampleStream, workers: int = 1, prefetch_batches: int = 4,
                  pin_memory: bool = False) -> DataLoader:
    """A DataLoader over ``stream`` (``workers = 0``: generated in this process). It has its own
    torch generator, so starting it never draws from torch's global RNG (a resumed run's RNG
    stream stays the same as an uninterrupted one's)."""
    generator = torch.Generator().manual_seed(stream.seed)
    return DataLoader(stream, batch_size=None, num_workers=workers, generator=generator,
                      prefetch_factor=prefetch_batches if workers > 0 else None,
                      worker_init_fn=_worker_init if workers > 0 else None,
                      pin_memory=pin_memory)


def validation_samples(ct: TrainingCT, simulation: SimulationConfig, pose: str, seed: int,
                       count: int, bone: BoneModel | None = None) -> list[Sample]:
    """The fixed held-out validation set: samples ``validation_rng(seed, j)``, ``j < count``."""
    bone = bone or BoneModel((ct.vertices, ct.faces))
    return [make_sample(bone, ct, simulation, pose, validation_rng(seed, j))
            for j in range(count)]
