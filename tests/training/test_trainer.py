"""The trainer: presets, schedule, run folder, epoch log, checkpoints, resume after a kill."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from comreg_core.config import ConfigError
from comreg_core.io.meshes import SurfaceMesh, write_mesh
from comreg_core.model.comreg import ComRegNet
from comreg_core.training import (LOG_COLUMNS, CheckpointError, load_checkpoint,
                                  mesh_fingerprint, pretrain, pretrain_preset)
from comreg_core.training.config import config_from_yaml, config_to_yaml
from comreg_core.training.checkpoint import network_warning
from comreg_core.training.step import build_optimizers
from comreg_core.training.trainer import BudgetTooShortError
from tests.helpers import FIBULA_STL
from tests.training.tiny import TINY, TINY_EPOCHS, tiny_run


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_paper_preset_is_the_papers_schedule():
    cfg = pretrain_preset("paper")
    t = cfg.training
    assert (t.samples_per_epoch, t.batch_size, t.epochs) == (2048, 4, 500)
    assert (t.lr_backbone, t.weight_decay_backbone, t.lr_head) == (1e-4, 5e-4, 1e-4)
    assert (t.lr_decay, t.lr_decay_epochs) == (0.9, 20)
    assert (cfg.model.loss.rho, cfg.model.loss.lambda_coarse, cfg.model.loss.lambda_fine) == (
        0.1, 1.0, 0.5)
    assert cfg.simulation.n_points == 20_000 and cfg.data.ct_points == 20_000
    assert cfg.data.pose == "paper" and cfg.simulation.mode == "sweep"
    cpu = pretrain_preset("cpu")
    assert cpu.simulation.n_points == cpu.model.completion.input_points == 2048
    with pytest.raises(ConfigError):
        pretrain_preset("gpu")
    with pytest.raises(ConfigError):
        pretrain_preset("cpu", {"training": {"samples_per_epoch": 10, "batch_size": 4}})


def test_an_old_run_config_with_retired_keys_loads():
    """Configs of runs made before ``training.world_size`` and ``model.pose.features`` were
    retired (config.yaml, a checkpoint's config_yaml) load as today's; the encoder-feature
    pose head is refused."""
    cfg = pretrain_preset("cpu", TINY)
    old = yaml.safe_load(config_to_yaml(cfg))
    old["training"]["world_size"] = 2
    old["model"]["pose"]["features"] = "decoded"
    assert config_from_yaml(yaml.safe_dump(old)) == cfg
    old["model"]["pose"]["features"] = "encoded"
    with pytest.raises(ConfigError, match="'model.pose.features' = 'encoded'.*removed"):
        config_from_yaml(yaml.safe_dump(old))


def test_optimizers_and_lr_schedule():
    cfg = pretrain_preset("cpu", TINY)
    model = ComRegNet(cfg.model)
    # the paper's schedule, with one step per epoch so that epochs and steps coincide
    paper = pretrain_preset("paper", {"training": {"samples_per_epoch": 4}}).training
    opts, scheds = build_optimizers(model, paper)
    assert isinstance(opts[0], torch.optim.AdamW) and opts[0].defaults["weight_decay"] == 5e-4
    assert type(opts[1]) is torch.optim.Adam
    lrs = []
    for _ in range(41):
        lrs.append(scheds[0].get_last_lr()[0])
        for o in opts:
            o.step()  # no gradients: a no-op, keeps the optimizer-then-scheduler order
        for s in scheds:
            s.step()
    assert lrs[0] == lrs[19] == pytest.approx(1e-4)
    assert lrs[20] == pytest.approx(0.9e-4) and lrs[40] == pytest.approx(0.81e-4)

    # the cpu preset: linear warm-up over 64 steps, then x0.9 every 4 epochs of 64 steps
    cpu = pretrain_preset("cpu").training
    opts, scheds = build_optimizers(model, cpu)
    lrs = []
    for _ in range(4 * 64 + 1):
        lrs.append([s.get_last_lr()[0] for s in scheds])
        for o in opts:
            o.step()
        for s in scheds:
            s.step()
    assert lrs[0] == pytest.approx([5e-4 / 64] * 2) and lrs[31] == pytest.approx([2.5e-4] * 2)
    assert lrs[63] == lrs[255] == pytest.approx([5e-4] * 2)
    assert lrs[256] == pytest.approx([4.5e-4] * 2)


def test_tiny_run_writes_a_reproducible_folder(tmp_path_factory):
    result, run_dir = tiny_run(tmp_path_factory)
    assert result.epochs == TINY_EPOCHS and result.stopped == "epochs"
    assert result.samples_seen == TINY_EPOCHS * 16
    cfg = config_from_yaml((run_dir / "config.yaml").read_text())
    assert cfg.seed == 0 and cfg.preset == "cpu" and cfg.training.epochs == TINY_EPOCHS
    assert cfg.model.completion.input_points == 256 and cfg.ct_mesh == str(FIBULA_STL)
    assert cfg == pretrain_preset("cpu", {**TINY, "ct_mesh": str(FIBULA_STL),
                                          "training": {**TINY["training"],
                                                       "epochs": TINY_EPOCHS,
                                                       "device": "cpu"}})
    fp = yaml.safe_load((run_dir / "ct_fingerprint.json").read_text())
    assert fp == mesh_fingerprint(FIBULA_STL) and len(fp["sha256"]) == 64

    rows = _rows(run_dir / "training_log.csv")
    assert list(rows[0]) == list(LOG_COLUMNS)
    assert [int(r["epoch"]) for r in rows] == list(range(TINY_EPOCHS + 1))
    assert all(float(r["val_RTE_mm_median"]) >= 0 for r in rows)
    assert all(np.isfinite(float(r["loss"])) for r in rows[1:])
    # learning shows on the fixed held-out set: the completion error falls clearly
    first, last = float(rows[0]["val_completion"]), float(rows[-1]["val_completion"])
    print(f"held-out completion loss {first:.3f} -> {last:.3f}; median RTE "
          f"{rows[0]['val_RTE_mm_median']} -> {rows[-1]['val_RTE_mm_median']} mm "
          f"(initial misalignment {result.initial_error['RTE_mm_median']:.1f} mm)")
    assert last < 0.8 * first

    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert state["epoch"] == TINY_EPOCHS and state["step"] == 0
    assert state["ct_fingerprint"] == fp["sha256"]
    for key in ("model", "optimizer_backbone", "optimizer_head", "scheduler_backbone",
                "scheduler_head", "world_size", "ct_points", "config_yaml"):
        assert key in state, key


def test_resume_after_kill_continues_exactly(tmp_path):
    overrides = {**TINY, "training": {**TINY["training"], "checkpoint_minutes": 1e-6,
                                      "samples_per_epoch": 8, "validation_sweeps": 2}}
    ref = pretrain(FIBULA_STL, tmp_path / "ref", preset="cpu", config=overrides, epochs=3,
                   device="cpu")

    class Killed(Exception):
        pass

    def kill_in_epoch_2(done, total, note=""):
        if done == 3:  # the first step of epoch 2 (2 steps per epoch): checkpoint just written
            raise Killed

    run = tmp_path / "run"
    with pytest.raises(Killed):
        pretrain(FIBULA_STL, run, preset="cpu", config=overrides, epochs=3, device="cpu",
                 progress=kill_in_epoch_2)
    state = load_checkpoint(run)
    assert (state["epoch"], state["step"], state["samples_seen"]) == (1, 1, 12)
    # the same folder without --resume is refused; with --resume it continues
    with pytest.raises(CheckpointError, match="resume"):
        pretrain(FIBULA_STL, run, preset="cpu", config=overrides, epochs=3, device="cpu")
    resumed = pretrain(FIBULA_STL, run, resume=True, device="cpu")
    assert resumed.epochs == 3 and resumed.samples_seen == 24
    rows = _rows(run / "training_log.csv")
    assert [int(r["epoch"]) for r in rows] == [0, 1, 2, 3]
    a = torch.load(run / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(ref.checkpoint, weights_only=True)["model"]
    worst = max(float((a[k].float() - b[k].float()).abs().max()) for k in a)
    assert worst < 1e-4, worst
    ref_rows = _rows(tmp_path / "ref" / "training_log.csv")
    assert float(rows[-1]["loss"]) == pytest.approx(float(ref_rows[-1]["loss"]), rel=1e-3)

    # extending a finished run: more epochs on resume
    more = pretrain(FIBULA_STL, run, resume=True, epochs=4, device="cpu")
    assert more.epochs == 4


def test_a_budget_shorter_than_one_epoch_is_an_error_and_the_run_resumes(tmp_path):
    with pytest.raises(BudgetTooShortError, match="before the first epoch") as caught:
        pretrain(FIBULA_STL, tmp_path / "run", preset="cpu", config=TINY, epochs=50,
                 max_minutes=1e-6, device="cpu")
    result = caught.value.result
    assert result.stopped == "time" and result.epochs == 0
    state = load_checkpoint(tmp_path / "run")
    assert state["epoch"] == 0 and state["samples_seen"] == result.samples_seen
    assert "has not been trained" in network_warning(state)
    resumed = pretrain(FIBULA_STL, tmp_path / "run", resume=True, epochs=1, max_minutes=0,
                       device="cpu")
    assert resumed.epochs == 1 and resumed.stopped == "epochs"


def test_the_budget_covers_the_whole_call(tmp_path, monkeypatch):
    """The budget counts from the call (set-up included) and leaves room for the next step and
    the validation that ends an epoch: a clock that jumps 0.4 s at every reading lets a 1-epoch
    budget end the run before epoch 2, whatever the machine's speed."""
    import itertools

    from comreg_core.training import trainer

    ticks = itertools.count()
    monkeypatch.setattr(trainer.time, "monotonic", lambda: 0.4 * next(ticks))
    with pytest.raises(BudgetTooShortError):
        pretrain(FIBULA_STL, tmp_path / "a", preset="cpu", config=TINY, epochs=5,
                 max_minutes=0.4 / 60, device="cpu")
    result = pretrain(FIBULA_STL, tmp_path / "b", preset="cpu", config=TINY, epochs=5,
                      max_minutes=20.0 / 60, device="cpu")
    assert result.stopped == "time" and 1 <= result.epochs < 5


def test_resume_with_another_ct_is_refused(tmp_path):
    import trimesh

    run = tmp_path / "run"
    with pytest.raises(BudgetTooShortError):
        pretrain(FIBULA_STL, run, preset="cpu", config=TINY, max_minutes=1e-6, device="cpu")
    capsule = trimesh.creation.capsule(height=60.0, radius=10.0)
    other = write_mesh(SurfaceMesh(np.asarray(capsule.vertices), np.asarray(capsule.faces)),
                       tmp_path / "capsule.stl")
    with pytest.raises(CheckpointError, match="another CT"):
        pretrain(other, run, resume=True, device="cpu")
    with pytest.raises(CheckpointError, match="no checkpoint.pt"):
        pretrain(other, tmp_path / "empty", resume=True, device="cpu")


def test_not_learned_warning_judges_by_the_share_of_sweeps_the_network_turns_right():
    initial = {"RRE_deg_median": 62.0, "RTE_mm_median": 55.0}

    def state(median, share=None):
        validation = {"val_coarse_RRE_deg_median": median}
        if share is not None:
            validation["val_coarse_improved_share"] = share
        return {"epoch": 36, "validation": validation, "initial_error": initial}

    # A bimodal validation (half the sweeps turned right, half left where they lie) has a
    # median that may land in either group; the share says the network has learned.
    assert network_warning(state(63.0, share=0.5)) is None
    warning = network_warning(state(12.0, share=0.04))
    assert "has not learned" in warning and "4%" in warning and "\n" not in warning
    # checkpoints validated before the share was logged: the median against the initial poses'
    assert network_warning(state(20.0)) is None
    assert "no better than the initial poses' (62 deg)" in network_warning(state(50.0))


def test_validation_share_is_zero_for_a_network_that_leaves_sweeps_where_they_lie():
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.training.config import pretrain_preset
    from comreg_core.training.data import TrainingCT, validation_samples
    from comreg_core.training.validation import identity_errors, validate
    from comreg_core.io.meshes import read_mesh

    cfg = pretrain_preset("cpu", {**TINY, "model": {**TINY["model"], "pose": {
        **TINY["model"]["pose"], "head": "mlp"}}})
    mesh = read_mesh(FIBULA_STL)
    ct = TrainingCT.from_mesh(mesh.vertices, mesh.faces, 512, seed=0)
    samples = validation_samples(ct, cfg.simulation, cfg.data.pose, 0, 6)
    net = ComRegNet(cfg.model)
    torch.nn.init.zeros_(net.pose_head.out.weight)  # the pose: exactly its bias, the identity
    norm = ct.normalization
    points = torch.from_numpy(norm.points_to_model(ct.points)).float()
    val = validate(net, points, samples, norm, surface=CTSurface((mesh.vertices, mesh.faces)))
    assert val["val_coarse_improved_share"] == 0.0
    assert val["val_coarse_RRE_deg_median"] == pytest.approx(
        identity_errors(samples, norm)["RRE_deg_median"], abs=1e-3)
