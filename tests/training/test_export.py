"""export_model: a registration-only copy of a run that registers like the run itself."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.registration.geometry.metrics import rotation_error_deg
from comreg_core.register import Registrar
from comreg_core.training import CheckpointError, export_model, load_checkpoint, pretrain
from comreg_core.training.data import TrainingCT, validation_samples
from tests.helpers import FIBULA_STL
from tests.training.tiny import tiny_run


def test_exported_model_is_smaller_and_registers_like_the_run(tmp_path_factory, tmp_path):
    run_dir = tiny_run(tmp_path_factory)[1]
    exported = export_model(run_dir, tmp_path / "model.pt")
    full, slim = load_checkpoint(run_dir), load_checkpoint(exported)
    assert "optimizer_backbone" not in slim and slim["ct_fingerprint"] == full["ct_fingerprint"]
    assert all(t.dtype.is_floating_point is False or str(t.dtype) == "torch.float16"
               for t in slim["model"].values())
    assert exported.stat().st_size < 0.5 * (run_dir / "checkpoint.pt").stat().st_size

    original = Registrar.from_run(run_dir, device="cpu")
    copy = Registrar.from_run(exported, device="cpu")
    ct = TrainingCT(original._ct_vertices, original._ct_faces, original.ct_points,
                    original.normalization)
    sample = validation_samples(ct, original.config.simulation, "paper", 7, 1)[0]
    points = original.normalization.points_to_mm(sample.source)
    # the network pass itself (the pose search may pick another of two near-equal poses)
    a = original.register(points, search=False)
    b = copy.register(points, search=False)
    # float16 weights: the same registration up to rounding (mm, degrees)
    assert np.abs(a.T_ct_us[:3, 3] - b.T_ct_us[:3, 3]).max() < 1.0
    assert rotation_error_deg(a.T_ct_us, b.T_ct_us) < 1.0

    with pytest.raises(CheckpointError, match="exported model"):
        pretrain(FIBULA_STL, exported.parent, resume=True) if exported.name == "checkpoint.pt" \
            else _resume_from(exported, tmp_path)


def _resume_from(exported, tmp_path):
    run = tmp_path / "exported_run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(exported.read_bytes())
    pretrain(FIBULA_STL, run, resume=True)
