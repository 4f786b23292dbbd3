"""Slow: the ``cpu`` preset trained for a few minutes on the fibula registers held-out simulated
sweeps far better than the initial misalignment (issue 5, "Done when"). Run with ``-m slow``."""

from __future__ import annotations

import pytest

from tests.helpers import FIBULA_STL

MINUTES = 8.0


@pytest.mark.slow
def test_cpu_preset_error_falls_well_below_the_initial_error(tmp_path):
    """Deselected by default (pyproject addopts: -m 'not slow')."""
    from comreg_core.training import pretrain

    result = pretrain(FIBULA_STL, tmp_path / "run", preset="cpu", max_minutes=MINUTES, seed=0,
                      device="cpu")
    val, init = result.validation, result.initial_error
    print(f"after {result.epochs} epochs: median RTE {init['RTE_mm_median']:.1f} -> "
          f"{val['val_RTE_mm_median']:.1f} mm, RRE {init['RRE_deg_median']:.1f} -> "
          f"{val['val_RRE_deg_median']:.1f} deg, success {val['val_success_rate']:.2f}")
    assert val["val_RTE_mm_median"] < 0.5 * init["RTE_mm_median"]
    assert val["val_RRE_deg_median"] < 0.5 * init["RRE_deg_median"]
