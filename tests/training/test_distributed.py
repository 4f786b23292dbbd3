"""Pretraining on several processes: torchrun + DDP on the CPU (gloo), against one process.

The torchrun tests start real jobs of 2 processes (one torch thread each) on a tiny network and
the fibula, 10-20 s each on 2 busy cores. Jobs whose losses are compared run
:mod:`tests.training.fixed_fps_cli` (the ``comreg`` command with fixed FPS starts, see there);
the others run ``-m comreg_core.cli`` itself.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.training import load_checkpoint, pretrain, pretrain_preset
from comreg_core.training.data import SampleStream, TrainingCT
from comreg_core.training.distributed import DistributedError, World
from tests.helpers import FIBULA_STL, assert_close
from tests.training.fixed_fps_cli import fix_fps_starts
from tests.training.tiny import TINY

REPO = Path(__file__).resolve().parents[2]
FIXED_FPS_CLI = "tests.training.fixed_fps_cli"

#: The tiny network, 2 steps of global batch 4 per epoch, samples made inline (no data workers),
#: the paper's learning rate (at 1e-3 Adam's sign-like first steps amplify float rounding into
#: percent-level loss differences within a few steps, which would hide what is compared), and
#: the retired ``training.world_size`` of old configs (3), which no launch may take for its own.
DDP_TINY = {**TINY, "data": {**TINY["data"], "workers": 0},
            "training": {**TINY["training"], "samples_per_epoch": 8, "validation_sweeps": 2,
                         "lr_backbone": 1e-4, "lr_head": 1e-4, "world_size": 3}}

#: Relative tolerance on epoch-mean losses of 2 processes (batch 2 each) vs 1 (batch 4), same
#: samples and FPS starts: measured 1e-7 at the first step and ~1e-5 after 4 steps (float32
#: sums in another order and batch shape; Adam's first steps magnify them).
LOSS_RTOL = 1e-4


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _config_file(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(DDP_TINY))
    return path


def _torchrun_command(nproc: int, args: list[str], *, module: str = "comreg_core.cli",
                      max_restarts: int = 0) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone",
            f"--nproc_per_node={nproc}", f"--max-restarts={max_restarts}", "-m", module, *args]


def _environment() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["OMP_NUM_THREADS"] = "1"  # one torch thread per process
    return env


def torchrun(nproc: int, args: list[str], timeout: float = 240, **kwargs
             ) -> subprocess.CompletedProcess:
    """Run a torchrun job to its end (stdout and stderr captured as text)."""
    return subprocess.run(_torchrun_command(nproc, args, **kwargs), env=_environment(), cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def _pretrain_args(run: Path, config: Path, epochs: int) -> list[str]:
    return ["pretrain", str(FIBULA_STL), "--out", str(run), "--preset", "cpu", "--epochs",
            str(epochs), "--device", "cpu", "--config", str(config)]


def _stray_files(run: Path) -> list[str]:
    """Temporary files of an interrupted atomic write."""
    return [p.name for p in run.iterdir() if ".tmp" in p.name]


# --- in-process checks of the pieces ------------------------------------------------------------

def test_world_from_torchrun_environment():
    assert World.from_environment({}) == World()
    world = World.from_environment({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1",
                                    "TORCHELASTIC_RESTART_COUNT": "2"})
    assert (world.rank, world.size, world.local_rank, world.launched, world.restart) == (
        3, 4, 1, True, 2)
    assert not world.is_main and World().is_main
    with pytest.raises(DistributedError, match="not started by torchrun"):
        World.from_environment({"RANK": "0", "WORLD_SIZE": "2"})
    with pytest.raises(DistributedError, match="inconsistent"):
        World.from_environment({"RANK": "2", "WORLD_SIZE": "2", "LOCAL_RANK": "0"})
    with pytest.raises(DistributedError, match="does not split evenly over 3 processes"):
        World(0, 3, 0, True).check_batch(4)
    World(1, 2, 1, True).check_batch(4)
    # a plain run: the collectives are the identity, the device is kept
    values = torch.tensor([1.0, 2.0], requires_grad=True)
    assert torch.equal(World().mean(values), values.detach())
    assert World().main_decides(True, torch.device("cpu")) is True
    assert World(1, 2, 1, True).device(torch.device("cpu")) == torch.device("cpu")
    # the retired training.world_size: any value of an old config is dropped (torchrun decides)
    assert pretrain_preset("cpu", {"training": {"world_size": 0}}) == pretrain_preset("cpu")


def test_processes_draw_disjoint_parts_of_the_same_global_batches():
    """Rank r of W takes samples r*n ... r*n+n-1 of every global batch (n = batch / W): the
    parts are disjoint and together are the one-process batches, sample for sample."""
    cfg = pretrain_preset("cpu", DDP_TINY)
    ct = TrainingCT.from_mesh(*_fibula_arrays(), cfg.data.ct_points, seed=0)

    def batches(rank: int, processes: int, count: int = 2) -> list[dict]:
        stream = SampleStream(ct, cfg.simulation, "paper", 0, batch_size=4, start=8, rank=rank,
                              processes=processes)
        it = iter(stream)
        return [next(it) for _ in range(count)]

    whole = batches(0, 1)
    parts = [batches(r, 2) for r in range(2)]
    for b in range(2):
        assert whole[b]["index"].tolist() == list(range(8 + 4 * b, 12 + 4 * b))
        for key in ("index", "source", "gt_points", "gt_transform"):
            joined = torch.cat([parts[0][b][key], parts[1][b][key]])
            assert torch.equal(joined, whole[b][key]), key
    with pytest.raises(ValueError, match="cannot split"):
        SampleStream(ct, cfg.simulation, "paper", 0, batch_size=4, rank=0, processes=3)


def _fibula_arrays():
    from comreg_core.io.meshes import read_mesh

    mesh = read_mesh(FIBULA_STL)
    return mesh.vertices, mesh.faces


def test_the_network_has_no_batch_statistics():
    """GroupNorm and LayerNorm normalise per sample: DDP needs no SyncBatchNorm."""
    from comreg_core.model.comreg import ComRegNet

    for preset in ("cpu", "paper"):
        net = ComRegNet(pretrain_preset(preset).model)
        kinds = {type(m).__name__ for m in net.modules() if "Norm" in type(m).__name__}
        assert kinds <= {"GroupNorm", "GroupNormLast", "LayerNorm"}, kinds
        assert not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
                       for m in net.modules())


# --- torchrun jobs ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_process_run(tmp_path_factory):
    """2 epochs of DDP_TINY on 2 processes with fixed FPS starts: ``(run_dir, job, seconds)``."""
    folder = tmp_path_factory.mktemp("two_process_run")
    started = time.monotonic()
    job = torchrun(2, _pretrain_args(folder / "run", _config_file(folder), 2),
                   module=FIXED_FPS_CLI)
    assert job.returncode == 0, job.stderr[-3000:]
    return folder / "run", job, time.monotonic() - started


def test_two_processes_match_one_with_the_same_global_batch(tmp_path, monkeypatch,
                                                            two_process_run):
    """2 epochs on 2 gloo processes (batch 2 each) vs 1 process (batch 4): the same epoch losses
    within LOSS_RTOL, one checkpoint written by rank 0, loaded by a single-process register."""
    run, job, job_s = two_process_run
    assert job.stdout.count("wrote ") == 1 and "x 2 processes" in job.stdout  # rank 0 alone

    fix_fps_starts(monkeypatch)
    started = time.monotonic()
    one = pretrain(FIBULA_STL, tmp_path / "one", preset="cpu", config=_config_file(tmp_path),
                   epochs=2, device="cpu")
    one_s = time.monotonic() - started
    assert one.world_size == 1  # recorded as 1 although the --config file says 3; config.yaml
    assert "world_size" not in yaml.safe_load(  # no longer holds it
        (tmp_path / "one" / "config.yaml").read_text())["training"]

    two_rows, one_rows = _rows(run / "training_log.csv"), _rows(tmp_path / "one" /
                                                                "training_log.csv")
    assert [r["world_size"] for r in two_rows] == ["2", "2", "2"]
    assert [r["samples"] for r in two_rows] == [r["samples"] for r in one_rows] == ["0", "8", "16"]
    for key in ("loss", "completion", "registration"):
        two = [float(r[key]) for r in two_rows[1:]]
        ref = [float(r[key]) for r in one_rows[1:]]
        print(f"{key}: 2 processes {two}, 1 process {ref}, relative difference "
              f"{np.max(np.abs(np.subtract(two, ref)) / np.abs(ref)):.2e}")
        assert_close(two, ref, rtol=LOSS_RTOL, what=f"epoch-mean {key}")
    print(f"torchrun job {job_s:.1f} s, one process {one_s:.1f} s")

    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoint.pt", "config.yaml", "ct_fingerprint.json", "training_log.csv"]
    state = load_checkpoint(run)
    assert (state["epoch"], state["samples_seen"], state["world_size"]) == (2, 16, 2)

    from comreg_core.io import PointCloud, read_mesh, write_points

    points = read_mesh(FIBULA_STL).to_trimesh().sample(3000, seed=1)
    write_points(PointCloud(points[points[:, 2] > np.percentile(points[:, 2], 70)]),
                 tmp_path / "us.ply")
    result = CliRunner().invoke(app, ["register", str(tmp_path / "us.ply"), "--model", str(run),
                                      "--ct", str(FIBULA_STL), "--no-search", "--device",
                                      "cpu", "--out", str(tmp_path / "reg")])
    assert result.exit_code == 0, result.output
    T = np.asarray(yaml.safe_load((tmp_path / "reg" / "result.json").read_text())["T_ct_us"])
    assert_close(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9, what="rotation")


def _kill_rank_mid_run(command: list[str], run: Path, rank: int) -> subprocess.Popen:
    """Start a torchrun job that checkpoints after every step; SIGKILL its process ``rank`` once
    a checkpoint newer than the first one seen is written (mid-run). Returns the job."""
    import psutil

    job = subprocess.Popen(command, env=_environment(), cwd=REPO, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, start_new_session=True)
    checkpoint = run / "checkpoint.pt"
    first = None
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and job.poll() is None:
        try:
            written = checkpoint.stat().st_mtime_ns
        except FileNotFoundError:
            written = None
        if first is None:
            first = written
        elif written != first:
            break
        time.sleep(0.02)
    assert job.poll() is None, "the job ended before it could be killed"
    victims = [p for p in psutil.Process(job.pid).children(recursive=True)
               if _environ(p).get("RANK") == str(rank)]
    assert len(victims) == 1, victims
    victims[0].send_signal(signal.SIGKILL)
    return job


def _environ(process) -> dict:
    try:
        return process.environ()
    except Exception:  # a process that already ended, or not ours to read
        return {}


def test_a_killed_process_stops_the_job_and_the_run_resumes_exactly(tmp_path, two_process_run):
    """Rank 1 killed (SIGKILL) mid-run: torchrun stops rank 0, which says so in one line and
    exits 2; the checkpoint is intact; the same command with --resume completes the run with
    the weights of the uninterrupted run (bit for bit), and a copy resumes on 1 process."""
    reference, _, _ = two_process_run
    over = {**DDP_TINY, "training": {**DDP_TINY["training"], "checkpoint_minutes": 1e-6}}
    config = tmp_path / "every_step.yaml"
    config.write_text(yaml.safe_dump(over))
    run = tmp_path / "run"
    started = time.monotonic()
    job = _kill_rank_mid_run(_torchrun_command(2, _pretrain_args(run, config, 2),
                                               module=FIXED_FPS_CLI), run, rank=1)
    _, stderr = job.communicate(timeout=120)
    print(f"killed job ended after {time.monotonic() - started:.1f} s")
    assert job.returncode != 0
    errors = [line for line in stderr.splitlines() if line.startswith("error")]
    assert len(errors) == 1 and "--resume" in errors[0], stderr[-3000:]
    assert "exitcode  : 2" in stderr and "SIGKILL" in stderr, stderr[-3000:]  # torchrun's report
    assert not _stray_files(run)
    state = load_checkpoint(run)
    assert 0 < state["samples_seen"] < 16 and state["world_size"] == 2
    print(f"{errors[0]}\nkilled after {state['samples_seen']} of 16 samples")

    import shutil

    shutil.copytree(run, tmp_path / "copy")
    started = time.monotonic()
    resumed = torchrun(2, ["pretrain", str(FIBULA_STL), "--out", str(run), "--resume"],
                       module=FIXED_FPS_CLI)
    print(f"resumed job {time.monotonic() - started:.1f} s")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    rows = _rows(run / "training_log.csv")
    ref_rows = _rows(reference / "training_log.csv")
    assert [r["epoch"] for r in rows] == ["0", "1", "2"]
    assert [r["loss"] for r in rows] == [r["loss"] for r in ref_rows]
    a, b = load_checkpoint(run)["model"], load_checkpoint(reference)["model"]
    assert all(torch.equal(a[k], b[k]) for k in a), "the resumed weights differ"

    # the same interrupted run resumed at another world size: 1 process
    single = pretrain(FIBULA_STL, tmp_path / "copy", resume=True, device="cpu")
    assert (single.epochs, single.samples_seen, single.world_size) == (2, 16, 1)
    sizes = [r["world_size"] for r in _rows(tmp_path / "copy" / "training_log.csv")]
    assert sizes[0] == "2" and sizes[-1] == "1" and len(sizes) == 3
    assert load_checkpoint(tmp_path / "copy")["world_size"] == 1


def test_torchrun_user_errors_are_one_line_and_exit_2(tmp_path):
    """A global batch of 3 cannot be split over 2 processes: the processes say so in one line
    each (tagged with the rank but for rank 0) and exit 2, before anything is written. (torchrun
    stops the others at the first failure, so not every process may get to say it.)"""
    over = {**DDP_TINY, "training": {**DDP_TINY["training"], "batch_size": 3,
                                     "samples_per_epoch": 6}}
    config = tmp_path / "batch3.yaml"
    config.write_text(yaml.safe_dump(over))
    job = torchrun(2, _pretrain_args(tmp_path / "run", config, 1))
    assert job.returncode != 0
    errors = [line for line in job.stderr.splitlines() if line.startswith("error")]
    assert errors and all("does not split evenly over 2 processes" in e for e in errors), \
        job.stderr[-3000:]
    assert {e.split(":")[0] for e in errors} <= {"error", "error (rank 1)"}
    assert "exitcode  : 2" in job.stderr  # torchrun's report of the failed process
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_torchrun_restarts_resume_the_run_and_the_budget_stops_every_rank_together(tmp_path,
                                                                                   monkeypatch):
    """``--max-restarts 1``: after rank 1 is killed, torchrun starts the job again and it
    continues its own run from the checkpoint (same weights as an uninterrupted run). A
    ``--max-minutes`` budget stops both processes at the same step (no hang, exit 0)."""
    over = {**DDP_TINY, "training": {**DDP_TINY["training"], "checkpoint_minutes": 1e-6}}
    config = tmp_path / "every_step.yaml"
    config.write_text(yaml.safe_dump(over))
    ref = torchrun(2, _pretrain_args(tmp_path / "ref", config, 2))
    assert ref.returncode == 0, ref.stderr[-3000:]
    run = tmp_path / "run"
    # without it, a restarted process may read the previous round's gloo address from the store
    # torchrun shares with the job (pytorch/pytorch#135712) and fail to connect
    monkeypatch.setenv("TORCH_DISABLE_SHARE_RDZV_TCP_STORE", "1")
    job = _kill_rank_mid_run(_torchrun_command(2, _pretrain_args(run, config, 2),
                                               max_restarts=1), run, rank=1)
    stdout, stderr = job.communicate(timeout=240)
    assert job.returncode == 0, stderr[-3000:]
    assert "wrote " in stdout and "x 2 processes" in stdout
    assert [r["epoch"] for r in _rows(run / "training_log.csv")] == ["0", "1", "2"]
    a, b = load_checkpoint(run)["model"], load_checkpoint(tmp_path / "ref")["model"]
    assert all(torch.equal(a[k], b[k]) for k in a), "the restarted run's weights differ"

    budget = torchrun(2, _pretrain_args(tmp_path / "budget", config, 1000)
                      + ["--max-minutes", "0.5"])
    assert budget.returncode == 0, budget.stderr[-3000:]
    assert "(stopped: time)" in budget.stdout
    state = load_checkpoint(tmp_path / "budget")
    assert 1 <= state["epoch"] < 1000 and state["world_size"] == 2
