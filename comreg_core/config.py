"""Typed configuration: dataclass sections with defaults, validated, loaded from and dumped to YAML.

Each package owns its section as a frozen dataclass (e.g. ``SimulationConfig`` in
``comreg_core.simulation``); this module is the one place that turns dicts/YAML into those
dataclasses and back, with clear errors for unknown keys, wrong types and out-of-range values.
Sections validate their own ranges in ``__post_init__`` by raising :class:`ConfigError`.
"""

from __future__ import annotations

import dataclasses
import logging
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from comreg_core.errors import ComRegError

T = TypeVar("T")

log = logging.getLogger(__name__)


class ConfigError(ComRegError):
    """A configuration value is unknown, of the wrong type, or out of range."""


def require(condition: bool, field: str, message: str) -> None:
    """Raise :class:`ConfigError` about ``field`` unless ``condition`` holds (range checks)."""
    if not condition:
        raise ConfigError(f"Config value '{field}' {message}.",
                          "Fix it in the config file or on the command line.")


#: A retired key's check: ``(value, section) -> True`` when the old value means what the code
#: does now (the key is then dropped), ``section`` being the whole section's dict.
RetiredCheck = Callable[[Any, dict], bool]


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build dataclass ``cls`` from a (possibly partial) dict; nested dataclasses recurse.

    Missing keys keep their defaults; unknown keys raise :class:`ConfigError` naming the valid ones.
    Keys of options that were removed (``cls.RETIRED_KEYS``: key -> :data:`RetiredCheck`), as
    old run folders and checkpoints still carry them, are dropped when they hold the value that
    survived and rejected otherwise.
    """
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"Config section '{where or cls.__name__}' must be a mapping.", "")
    data = _drop_retired(cls, dict(data or {}), where)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"Unknown config key(s) {', '.join(repr(k) for k in unknown)} in "
            f"'{where or cls.__name__}'.", f"Valid keys: {', '.join(fields)}.")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{where}.{name}" if where else name)
    return cls(**kwargs)


def _drop_retired(cls: type, data: dict[str, Any], where: str) -> dict[str, Any]:
    retired: dict[str, RetiredCheck] = getattr(cls, "RETIRED_KEYS", {})
    for key in [k for k in data if k in retired]:
        if not retired[key](data[key], data):
            name = f"{where}.{key}" if where else key
            raise ConfigError(
                f"Config value '{name}' = {data[key]!r} selects an option that has been removed.",
                "It was an experiment that lost (docs/results.md); remove the key from the "
                "config file.")
        del data[key]
    return data


def _coerce(hint, value, where: str):
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value, where)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(option, value, where)
            except ConfigError:
                continue
        raise ConfigError(f"Config value '{where}' = {value!r} has the wrong type ({hint}).", "")
    if origin is typing.Literal:
        if value not in typing.get_args(hint):
            raise ConfigError(f"Config value '{where}' = {value!r} is not one of "
                              f"{', '.join(map(repr, typing.get_args(hint)))}.", "")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"Config value '{where}' must be a list, got {value!r}.", "")
        args = typing.get_args(hint)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"Config value '{where}' needs {len(args)} items, got "
                                  f"{len(value)}.", "")
            return tuple(_coerce(a, v, where) for a, v in zip(args, value))
        item = args[0] if args else Any
        return origin(_coerce(item, v, where) for v in value)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"Config value '{where}' must be a number, got {value!r}.", "")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"Config value '{where}' must be an integer, got {value!r}.", "")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"Config value '{where}' must be true or false, got {value!r}.", "")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"Config value '{where}' must be text, got {value!r}.", "")
        return value
    return value


def to_dict(config) -> dict[str, Any]:
    """Plain dict (tuples as lists) of a dataclass config, ready for YAML."""

    def plain(value):
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value

    return plain(dataclasses.asdict(config))


def load_config(cls: type[T], path: str | Path | None = None, overrides: dict | None = None,
                section: str | None = None, ignore: tuple[str, ...] = (),
                renamed: dict[str, str] | None = None) -> T:
    """Defaults of ``cls``, updated from the YAML file at ``path`` then from ``overrides``.

    With ``section``, a file holding a mapping with that key (e.g. a run's ``config.yaml`` with
    ``simulation:`` beside other sections) contributes only that section; a file without the key
    is taken as the section's own keys. Top-level keys in ``ignore`` are left out (records a
    command writes beside its settings, e.g. ``inputs:``). ``renamed`` ``{old: new}``: a
    file's top-level section under its old name is read as the new one (one warning per file).
    """
    data: dict[str, Any] = {}
    if path is not None:
        data = {k: v for k, v in read_yaml_mapping(path).items() if k not in ignore}
        data = _rename_sections(data, renamed or {}, path)
        if section is not None and section in data:
            data = data[section] or {}
    merged = deep_merge(data, overrides or {})
    return from_dict(cls, merged, section or "")


#: ``(file, old section name)`` already warned about by :func:`_rename_sections`.
_WARNED_RENAMES: set[tuple[str, str]] = set()


def _rename_sections(data: dict[str, Any], renamed: dict[str, str],
                     path: str | Path) -> dict[str, Any]:
    """``data`` with its sections under an old name (``renamed`` ``{old: new}``) moved to
    the new name; a warning once per file and name, an error when both are there."""
    for old, new in renamed.items():
        if old not in data:
            continue
        if new in data:
            raise ConfigError(f"'{path}' has both a '{old}:' and a '{new}:' section.",
                              f"'{old}:' is the old name of '{new}:'; keep only '{new}:'.")
        data = {(new if k == old else k): v for k, v in data.items()}
        if (str(path), old) not in _WARNED_RENAMES:
            _WARNED_RENAMES.add((str(path), old))
            log.warning("'%s': the section '%s:' is now called '%s:' (read as such).",
                        path, old, new)
    return data


def parse_yaml_mapping(text: str, where: str) -> dict[str, Any]:
    """The mapping in YAML ``text`` (empty text -> ``{}``); ``where`` names it in errors."""
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where} is not valid YAML ({exc}).", "Fix the syntax.") from None
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{where} must hold a mapping of config keys.", "")
    return data or {}


def read_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """The mapping in the YAML file at ``path`` (checked to exist)."""
    from comreg_core.io._files import require_input_file

    path = require_input_file(path, "config file")
    return parse_yaml_mapping(path.read_text(encoding="utf-8"), f"'{path}'")


def write_config(config, path: str | Path) -> Path:
    """Write ``config`` as YAML atomically; returns the path."""
    import yaml

    from comreg_core.io._files import atomic_output

    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(yaml.safe_dump(to_dict(config), sort_keys=False), encoding="utf-8")
    return path


def deep_merge(base: dict, update: dict) -> dict:
    """``base`` updated by ``update``, merging nested mappings key by key (no input changed)."""
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out
