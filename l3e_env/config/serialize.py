"""Config dataclasses to and from dicts and YAML, and the comparison of stored settings."""

from __future__ import annotations

import dataclasses
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
        kwargs[key] = value
    return cls(**kwargs)


def dump_yaml(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(plain(to_dict(cfg)), sort_keys=False))


def load_yaml(cls: type[T], path: str | Path) -> T:
    return from_dict(cls, yaml.safe_load(Path(path).read_text()))


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
