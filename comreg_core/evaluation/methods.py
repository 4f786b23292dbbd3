"""Registration methods by name, as ``comreg evaluate --method`` offers them.

- ``search``: the pose search alone, no network (:meth:`~comreg_core.register.Registrar.
  from_ct`: starts from the principal axes of the US cloud on the CT's);
- ``comreg``: the pretrained run with the pose search (the default pipeline;
  :mod:`comreg_core.registration.search.search`);
- ``comreg-plain``: the same network without it (the paper's plain pipeline);
- ``ransac``, ``icp-gt``: the baselines (:mod:`.baselines`);
- ``all``: every one of them.

``comreg`` and ``comreg-plain`` share one loaded network (one
:class:`~comreg_core.register.Registrar`, its CT half encoded once); ``comreg-plain`` calls it
with ``search=False``.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from comreg_core.choices import BASELINES, COMREG_METHODS, METHODS, SEARCH_METHODS
from comreg_core.config import load_config
from comreg_core.errors import ComRegError
from comreg_core.evaluation.baselines import BaselineConfig, baseline_methods
from comreg_core.register import Registrar
from comreg_core.registration import SearchConfig, as_search_config
from comreg_core.registration.search.config import RENAMED_SECTIONS
from comreg_core.simulation.config import SimulationConfig


def method_names(names: str | Iterable[str]) -> list[str]:
    """The requested names with ``all`` expanded and duplicates dropped, in the order given;
    unknown names raise :class:`ComRegError` listing the known ones."""
    names = [names] if isinstance(names, str) else list(names)
    out: list[str] = []
    for name in names:
        for item in (METHODS if name == "all" else (name,)):
            if item not in METHODS:
                raise ComRegError(f"Unknown registration method '{item}'.",
                                  f"Use one of: {', '.join(METHODS)}, all.")
            if item not in out:
                out.append(item)
    if not out:
        raise ComRegError("No registration method was chosen.",
                          f"Use one or more of: {', '.join(METHODS)}, all.")
    return out


@dataclass(frozen=True)
class EvaluateConfig:
    """The settings of ``comreg evaluate --config FILE``: sections ``search:`` (the pose
    search of ``search`` and ``comreg``; ``hypotheses:``, its older name, is read as such),
    ``baselines:`` (``ransac:``, ``icp_gt:``) and ``simulation:`` (the sweeps of
    ``simulated``, e.g. short one-face sweeps:
    ``trajectory: {length_mm: [40, 50], side_drift_deg: 20, longitudinal_probability: 0}``)."""

    search: SearchConfig = field(default_factory=SearchConfig)
    baselines: BaselineConfig = field(default_factory=BaselineConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)


def load_evaluate_config(path: str | Path | None = None,
                         overrides: dict | None = None) -> EvaluateConfig:
    """:class:`EvaluateConfig` from a YAML file (None: the defaults) and ``overrides``; a
    registration's ``config.yaml`` works too (its ``inputs:`` record is ignored)."""
    return load_config(EvaluateConfig, path, overrides, ignore=("inputs",),
                       renamed=RENAMED_SECTIONS)


def registration_methods(names: str | Iterable[str], run_dir, ct_mesh, *, device: str = "auto",
                         seed: int = 0, search=None,
                         baseline_config: BaselineConfig | None = None) -> dict[str, Any]:
    """``{name: method}`` for :func:`~comreg_core.evaluation.evaluate`.

    Args:
        names: method names (:data:`METHODS`, or ``all``).
        run_dir: the pretrained run (needed for ``comreg`` / ``comreg-plain``; None without).
        ct_mesh: the CT surface (``search``, the baselines; a fingerprint check of the run).
        device: where the network runs.
        seed: the baselines' seed.
        search: the pose search's settings of ``comreg`` and ``search`` (None = the
            defaults; see :class:`~comreg_core.registration.SearchConfig`).
        baseline_config: the baselines' settings.
    """
    names = method_names(names)
    alone = {}
    if any(name in SEARCH_METHODS for name in names):
        alone["search"] = Registrar.from_ct(ct_mesh, search=search)
    comreg = {}
    if any(name in COMREG_METHODS for name in names):
        if run_dir is None:
            raise ComRegError(f"The method(s) {', '.join(n for n in names if n in COMREG_METHODS)}"
                              " need a pretrained run.",
                              "Give --model RUN_DIR (from 'comreg pretrain'), or evaluate "
                              "'search' and the baselines alone.")
        config = as_search_config(search)
        if "comreg" in names and not config.enabled:
            raise ComRegError("The 'comreg' method was asked for with its pose search off.",
                              "Use the method 'comreg-plain' for the plain pipeline.")
        registrar = Registrar.from_run(run_dir, device, ct_mesh=ct_mesh, search=config)
        plain = functools.partial(registrar.register, search=False)
        comreg = {"comreg": registrar, "comreg-plain": plain}
    baselines = [name for name in names if name in BASELINES]
    built = baseline_methods(baselines, ct_mesh, baseline_config, seed=seed) if baselines else {}
    available = {**alone, **comreg, **built}
    return {name: available[name] for name in names}
