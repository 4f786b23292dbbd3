"""The layers of docs/architecture.md, checked on the source: imports only go down, the
registration package stays free of torch and the network, no module grows past ~500 lines."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: comreg_core's layers, lowest first: a module may import its own layer and those below.
LAYERS = (
    ("errors", "transforms", "runs", "choices", "progress", "pointsets", "normalization"),
    ("config", "io"),
    ("surfaces",),
    ("registration",),
    ("simulation",),
    ("model",),
    ("training",),
    ("register",),
    ("evaluation",),
    ("report",),
    ("demo", "cli", "live", "batch"),
)
LAYER = {name: rank for rank, names in enumerate(LAYERS) for name in names}
MAX_LINES = 400
#: No function longer than this (lines, docstring included), compiled numba kernels aside.
MAX_FUNCTION_LINES = 80
#: The ``comreg`` command (``comreg_core/cli/``): short modules of short functions.
CLI_MAX_LINES = 400
CLI_MAX_FUNCTION_LINES = 60


def _modules(package: str) -> list[Path]:
    return sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)


def _unit(path: Path) -> str:
    """``comreg_core/registration/geometry/icp.py`` -> ``registration``; ``comreg_core/demo.py`` ->
    ``demo``."""
    return path.relative_to(ROOT / "comreg_core").parts[0].removesuffix(".py")


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in the file, inside functions too."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "comreg_core":  # from comreg_core import runs
                found += [(node.lineno, f"comreg_core.{a.name}") for a in node.names]
            else:
                found.append((node.lineno, node.module))
    return found


def test_every_comreg_core_unit_has_a_layer():
    units = {_unit(p) for p in _modules("comreg_core")} - {"__init__"}
    assert units <= set(LAYER), f"give these a layer here and in docs/architecture.md: " \
                                f"{sorted(units - set(LAYER))}"


def test_imports_only_go_down_the_layers():
    upward = []
    for path in _modules("comreg_core"):
        unit = _unit(path)
        if unit == "__init__":
            continue
        for line, module in _imports(path):
            parts = module.split(".")
            if parts[0] == "comreg_plugin":
                upward.append(f"{path.relative_to(ROOT)}:{line} imports the plugin")
            if parts[0] != "comreg_core" or len(parts) < 2 or parts[1].startswith("__"):
                continue
            if LAYER[parts[1]] > LAYER[unit]:
                upward.append(f"{path.relative_to(ROOT)}:{line} ({unit}) imports {module}")
    assert not upward, "\n".join(upward)


def test_registration_needs_no_torch_and_no_network():
    heavy = [f"{p.relative_to(ROOT)}:{line} imports {module}"
             for p in _modules("comreg_core/registration") for line, module in _imports(p)
             if module.split(".")[0] == "torch" or module.startswith("comreg_core.model")]
    assert not heavy, "\n".join(heavy)


@pytest.mark.parametrize("package", ["comreg_core", "comreg_plugin"])
def test_no_module_over_400_lines(package):
    long = {str(p.relative_to(ROOT)): n for p in _modules(package)
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert not long, f"split these by concern: {long}"


def _compiled(node) -> bool:
    """Whether a function is a numba kernel (``@njit`` or ``@numba.njit``, with arguments or
    not): one loop over points, not a pipeline of steps."""
    for decorator in node.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit"):
            return True
    return False


@pytest.mark.parametrize("package", ["comreg_core", "comreg_plugin"])
def test_functions_read_as_named_steps(package):
    long = {}
    for path in _modules(package):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                    not _compiled(node) and \
                    (n := node.end_lineno - node.lineno + 1) > MAX_FUNCTION_LINES:
                long[f"{path.relative_to(ROOT)}:{node.lineno} {node.name}()"] = n
    assert not long, f"split these into named steps (at most {MAX_FUNCTION_LINES} lines): {long}"


def test_the_cli_is_short_modules_of_short_functions():
    long = {}
    for path in _modules("comreg_core/cli"):
        text = path.read_text(encoding="utf-8")
        if (n := len(text.splitlines())) > CLI_MAX_LINES:
            long[str(path.relative_to(ROOT))] = n
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                    (n := node.end_lineno - node.lineno + 1) > CLI_MAX_FUNCTION_LINES:
                long[f"{path.relative_to(ROOT)}:{node.lineno} {node.name}()"] = n
    assert not long, f"split these into named steps (at most {CLI_MAX_LINES} lines a module, " \
                     f"{CLI_MAX_FUNCTION_LINES} a function): {long}"


def test_every_command_is_registered_one_way():
    """``@app.command(NAME, rich_help_panel=PANEL)`` on the command's function; never
    ``app.command(NAME)(function)``."""
    other = []
    for path in _modules("comreg_core/cli"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        decorators = {id(d) for node in ast.walk(tree)
                      if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                      for d in node.decorator_list}
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                    node.func.attr == "command" and (
                        id(node) not in decorators
                        or not any(k.arg == "rich_help_panel" for k in node.keywords)):
                other.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not other, "register commands with @app.command(NAME, rich_help_panel=PANEL): " \
                      + ", ".join(other)


def test_the_named_choices_are_what_the_packages_implement():
    from comreg_core import choices
    from comreg_core.evaluation.baselines import baseline_methods
    from comreg_core.training.config import PRESETS, pretrain_preset

    assert tuple(sorted(PRESETS)) == tuple(sorted(choices.PRESETS))
    for name in choices.PRESETS:
        assert pretrain_preset(name).preset == name
    from tests.helpers import FIBULA_STL

    assert set(baseline_methods(["icp-gt"], FIBULA_STL)) == {"icp-gt"}


#: The sub-packages of ``registration``, lowest first: each imports only those before it.
REGISTRATION_PARTS = ("geometry", "search", "judgement")


def test_registration_parts_import_only_downwards():
    rank = {name: k for k, name in enumerate(REGISTRATION_PARTS)}
    bad = []
    for path in _modules("comreg_core/registration"):
        parts = path.relative_to(ROOT / "comreg_core" / "registration").parts
        if len(parts) < 2:
            continue
        for line, module in _imports(path):
            pieces = module.split(".")
            if pieces[:2] == ["comreg_core", "registration"] and len(pieces) > 2 \
                    and pieces[2] in rank and rank[pieces[2]] > rank[parts[0]]:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    assert not bad, bad
