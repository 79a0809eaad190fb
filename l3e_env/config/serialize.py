"""Config dataclasses to and from dicts and YAML, and the comparison of stored settings."""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


def to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def from_dict(cls: type[T], data: dict[str, Any] | None) -> T:
    """Build a (nested) config dataclass, rejecting unknown keys by name."""
    data = dict(data or {})
    names = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]  # a dataclass by contract
    hints = _hints(cls)
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown option(s) {unknown}; known: {sorted(names)}")
    kwargs = {}
    for key, value in data.items():
        factory = names[key].default_factory
        default = factory() if callable(factory) else None
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = from_dict(type(default), value)
        elif isinstance(value, list):
            value = tuple(value)
        if (problem := _type_problem(hints.get(key), value)) is not None:
            raise ValueError(f"{cls.__name__}: option {key} takes {problem}, got {value!r:.80}")
        kwargs[key] = value
    return cls(**kwargs)


def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - a hint that does not resolve is not checked
        return {}


def _type_problem(hint: Any, value: Any) -> str | None:
    """What `hint` takes where `value` is not of it, else None: numbers, text, truth values, sequences,
    mappings, choices and their optional forms are checked; other hints are taken as they come (a
    YAML "8" for a whole number is a mistake to name before the work starts, not a TypeError after)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is None or hint is Any:
        return None
    if origin in (typing.Union, types.UnionType):
        problems = [_type_problem(a, value) for a in args]
        return None if any(p is None for p in problems) else " or ".join(p for p in problems if p)
    if hint is type(None):
        return None if value is None else "nothing"
    if origin is typing.Literal:
        return None if value in args else f"one of {list(args)}"
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "a whole number"
    if hint is float:
        return None if isinstance(value, (int, float)) and not isinstance(value, bool) else "a number"
    if hint is str:
        return None if isinstance(value, str) else "text"
    if hint is Path:
        return None if isinstance(value, (str, Path)) else "a path"
    if origin in (tuple, list) or hint in (tuple, list):
        return None if isinstance(value, (tuple, list)) else "a list"
    if origin is dict or hint is dict:
        return None if isinstance(value, dict) else "a mapping"
    if dataclasses.is_dataclass(hint):
        return None if isinstance(value, dict) or dataclasses.is_dataclass(value) else "a mapping of its settings"
    return None


def dump_yaml(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(plain(to_dict(cfg)), sort_keys=False))


def load_yaml(cls: type[T], path: str | Path) -> T:
    """A config from a YAML file (read safely: a tag that would run code is refused); ValueError naming
    the file where it is not readable YAML, not a mapping, or holds an unknown option or a mistyped value."""
    try:
        loaded = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot be read as {cls.__name__} YAML ({str(exc).splitlines()[0]})") from None
    if loaded is not None and not isinstance(loaded, dict):
        raise ValueError(f"{path}: give a YAML mapping of {cls.__name__}'s options, not a {type(loaded).__name__}")
    try:
        return from_dict(cls, loaded)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from None


def plain(x: Any) -> Any:
    """Tuples to lists, recursively: the form YAML, JSON and torch's weights-only loader keep."""
    if isinstance(x, dict):
        return {k: plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    return x


def with_defaults(cls: type, stored: dict[str, Any]) -> dict[str, Any]:
    """Stored settings of `cls` in plain form with every option they predate at its default: what
    was made before an option existed was made as that default makes it."""
    return plain(to_dict(from_dict(cls, stored)))


def settings_changed(before: dict[str, Any], now: dict[str, Any], prefix: str = "") -> str:
    """The settings that differ, named for an error message (a section's by its path, "fusion.backend"):
    the old and new values of the short ones, the names only of long ones (a mesh's route is a long list)."""

    def shown(key: str) -> str:
        old, new = before.get(key), now.get(key)
        if isinstance(old, dict) and isinstance(new, dict):
            return settings_changed(old, new, f"{prefix}{key}.")
        return f"{prefix}{key}" if len(repr(old)) + len(repr(new)) > 80 else f"{prefix}{key} {old!r}, now {new!r}"

    return ", ".join(shown(k) for k in sorted(before.keys() | now.keys()) if before.get(k) != now.get(k))
