"""Every command's options from a YAML file (`--config FILE.yaml`) and one at a time (`--set KEY=VALUE`),
and the options a run resolved, written beside what it made (`<out>/options.yaml`, or `<out>.options.yaml`
beside a file), so that `l3e COMMAND --config that.yaml` runs it again.

Keys are the option names of `l3e COMMAND --help`, without the leading dashes (`seeds`, `odometry-bias`
or `odometry_bias`). Precedence: `--set` over the command line over `--config` over the defaults. A YAML
file is read with `yaml.safe_load`: it cannot run code."""

from __future__ import annotations

import argparse
import functools
import math
from pathlib import Path
from typing import Any

import yaml

RESERVED = {"help", "config", "set", "func", "command", "_parser"}
OPTIONS_FILE = "options.yaml"


def leaf_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers that run a command (those without sub-commands), depth first."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [parser]
    return [leaf for action in subs for sub in action.choices.values() for leaf in leaf_parsers(sub)]


def add_option_files(parser: argparse.ArgumentParser) -> None:
    """--config (where the command has no --config of its own, as `l3e train` has) and --set on every
    command; each remembers its parser so that `resolve` can check the keys against it."""
    strict_types(parser)
    for leaf in leaf_parsers(parser):
        own = any(a.dest == "config" for a in leaf._actions)
        g = leaf.add_argument_group("options from a file")
        if not own:
            g.add_argument(
                "--config",
                metavar="FILE.yaml",
                help="take the options from this YAML mapping of option names to values (the "
                "options.yaml a run writes); the command line wins over it",
            )
        g.add_argument(
            "--set",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="set one option (KEY as in --help, without the dashes; VALUE in YAML); repeat",
        )
        # a required option may come from --config or --set: checked after them (`resolve`), not by argparse
        required = [(a.dest, a.option_strings[-1]) for a in leaf._actions if a.required and a.option_strings]
        for action in leaf._actions:
            if action.option_strings:
                action.required = False
        leaf.set_defaults(_parser=leaf, _options_file=not own, _required=required)


# The least value of each counted or measured option, by its name, on every command that has it: the
# command line, --set and --config all pass through the same check (`checked_type`)
MINIMUM = {
    "workers": 1,
    "every": 1,
    "episodes": 1,
    "seeds": 1,
    "parents": 1,
    "children": 1,
    "epochs": 1,
    "points": 1,
    "threads": 1,
    "envs": 1,
    "timesteps": 1,
    "samples_per_epoch": 1,
    "draws": 1,
    "max_steps": 1,
    "seed": 0,
    "sensor_index": 0,
    "start": 0.0,
    "end": 0.0,
    "scan_mc": 0,
    "detector_every": 1,
    "replay_share": 0.0,
    "imu_rate": 0.0,
    "lam": 0.0,
    "keyframe_distance": 0.0,
    "stop_radius": 1e-3,
    "resolution": 0.25,
    "max_scans": 20,
    "scale": 1e-9,
    "lr": 0.0,
    "beta": 1e-9,
    "soft_labels": 0.0,
}
# and at most (issue 90): a count or a size beyond any practical run is refused where it enters, before
# work is sized by it (processes: more than 64 is no machine's; each holds a scene)
MAXIMUM = {
    "workers": 64,
    "every": 100_000,
    "episodes": 10_000,
    "seeds": 1000,
    "parents": 100_000,
    "children": 10_000,
    "epochs": 10_000,
    "points": 1_000_000,
    "threads": 256,
    "envs": 64,
    "timesteps": 1_000_000_000,
    "samples_per_epoch": 10_000_000,
    "draws": 100_000,
    "max_steps": 1_000_000,
    "max_scans": 100_000,
    "sensor_index": 64,
    "start": 1e7,
    "end": 1e7,
    "scan_mc": 10_000,
    "detector_every": 100,
    "replay_share": 0.95,
    "imu_rate": 2000.0,
    "resolution": 50.0,
    "scale": 1e6,
    "soft_labels": 1000.0,
    "lam": 1e6,
    "keyframe_distance": 1000.0,
    "stop_radius": 1.0,  # the goal radius (EnvConfig.goal_radius): a stop farther out never arrives
    "lr": 10.0,
}


def checked_type(action: argparse.Action, name: str) -> Any:
    """The action's type, made strict: a whole number for `int` (never 2.5 or true), a finite number for
    `float` (never nan), at least the option's MINIMUM and at most its MAXIMUM; the message names the option."""
    base = action.type
    if base not in (int, float):
        return base
    least, most = MINIMUM.get(action.dest), MAXIMUM.get(action.dest)

    def check(text: str) -> int | float:
        try:
            value = base(text)
        except (TypeError, ValueError):
            kind = "a whole number" if base is int else "a number"
            raise argparse.ArgumentTypeError(f"{name} takes {kind}, got {text!r}") from None
        if base is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{name} takes a finite number, got {text!r}")
        if least is not None and value < least:
            raise argparse.ArgumentTypeError(f"{name} takes {least} or more, got {text!r}")
        if most is not None and value > most:
            raise argparse.ArgumentTypeError(f"{name} takes at most {most:g}, got {text!r}")
        return value

    check.__name__ = base.__name__  # argparse names the type in its own messages
    return check


def strict_types(parser: argparse.ArgumentParser) -> None:
    """Every command's int and float options checked by `checked_type`."""
    for leaf in leaf_parsers(parser):
        for action in leaf._actions:
            if action.option_strings:
                action.type = checked_type(action, action.option_strings[-1])


def _actions(leaf: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {
        a.dest: a
        for a in leaf._actions
        if a.dest not in RESERVED and a.dest != argparse.SUPPRESS and not a.dest.startswith("_")
    }


def _one(action: argparse.Action, key: str, v: Any) -> Any:
    """One value of an option as argparse would have made it from text; ValueError naming the key."""
    if not isinstance(v, str):  # a YAML number is read as its text; a list, map or boolean is no value here
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            if action.type is None:
                raise ValueError(f"option {key}: takes text (a path or a name), got {v!r}")
            raise ValueError(f"option {key}: {v!r} is not a value of this option")
        v = str(v)
    if callable(action.type):
        try:
            v = action.type(v)
        except (argparse.ArgumentTypeError, TypeError, ValueError) as exc:
            raise ValueError(f"option {key}: {exc}") from None
    if action.choices is not None and v not in action.choices:
        raise ValueError(f"option {key}: {v!r} is not one of {list(action.choices)}")
    return v


def _converted(action: argparse.Action, key: str, value: Any) -> Any:
    """`value` as argparse would have made it from the command line; ValueError naming the key. None is
    an option not given, as the defaults have it."""
    if value is None:
        return None

    one = functools.partial(_one, action, key)
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse.BooleanOptionalAction)):
        if not isinstance(value, bool):
            raise ValueError(f"option {key}: give true or false, got {value!r}")
        return value
    if isinstance(action, argparse._ExtendAction):  # each item converts to several ("yaw,scale")
        return [x for v in (value if isinstance(value, list) else [value]) for x in one(v)]
    if isinstance(action, argparse._AppendAction) or action.nargs in ("+", "*") or isinstance(action.nargs, int):
        return [one(v) for v in (value if isinstance(value, list) else [value])]
    if isinstance(value, list) and getattr(action.type, "__name__", "") in ("int", "float"):
        raise ValueError(f"option {key}: takes one number, got {value!r}")
    if isinstance(value, list) and action.type is not None:
        if not value:
            return ()
        value = ",".join(map(str, value))  # a comma-separated option written as a YAML list
    return one(value)


def _mapping(leaf: argparse.ArgumentParser, values: dict[str, Any], where: str) -> dict[str, Any]:
    actions = _actions(leaf)
    out = {}
    for raw, value in values.items():
        key = str(raw).replace("-", "_")
        if key not in actions:
            raise ValueError(
                f"{where}: {leaf.prog} has no option '{raw}' (its options: "
                f"{', '.join(sorted(k.replace('_', '-') for k in actions))})"
            )
        out[key] = _converted(actions[key], str(raw), value)
    return out


def read_options(path: str | Path, leaf: argparse.ArgumentParser) -> dict[str, Any]:
    """The options in a YAML file, checked and converted; ValueError naming the file and the problem."""
    try:
        loaded = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the options as YAML ({str(exc).splitlines()[0]})") from None
    if loaded is None:
        return {}
    if not isinstance(loaded, dict):
        raise ValueError(f"{path}: give a YAML mapping of option names to values, not a {type(loaded).__name__}")
    return _mapping(leaf, loaded, str(path))


def set_options(pairs: list[str], leaf: argparse.ArgumentParser) -> dict[str, Any]:
    values = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--set {pair!r}: give KEY=VALUE, e.g. --set seeds=5")
        try:
            values[key] = yaml.safe_load(text)
        except yaml.YAMLError:
            values[key] = text
        if values[key] is None:
            values[key] = text
    return _mapping(leaf, values, "--set")


def resolve(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse `argv` with the command's --config file as defaults and its --set pairs on top; ValueError
    (naming the file or the pair) for an unknown option or a value its type refuses."""
    args = parser.parse_args(argv)
    leaf = getattr(args, "_parser", None)
    if leaf is None:
        return args
    try:
        path = getattr(args, "config", None)
        own_run = path and not args._options_file and _is_options_file(path, leaf)
        if path and (args._options_file or own_run):
            options = read_options(path, leaf)
            leaf.set_defaults(**options)
            args = parser.parse_args(argv)  # the command line wins over the file
            if own_run:  # the run's options.yaml, given where --config names the command's own file
                args.config = None
        for key, value in set_options(args.set, leaf).items():
            setattr(args, key, value)
    except ValueError as exc:
        leaf.error(str(exc))
    if missing := [option for dest, option in args._required if getattr(args, dest, None) in (None, [])]:
        leaf.error(
            f"the following arguments are required: {', '.join(missing)} (on the command line, or in --config/--set)"
        )
    return args


def _is_options_file(path: str, leaf: argparse.ArgumentParser) -> bool:
    """Whether `path` is a run's options.yaml (a mapping of this command's options, its output among
    them) rather than the file a command's own --config reads (`l3e train`'s TrainConfig)."""
    try:
        loaded = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False  # the command's own reader names what is wrong
    dests = {a.dest for a in leaf._actions}
    keys = {str(k).replace("-", "_") for k in loaded} if isinstance(loaded, dict) else set()
    return "out" in keys and keys <= dests


def _plain(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def resolved_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options a run resolved, as `--config` reads them back."""
    leaf = args._parser
    return {k.replace("_", "-"): _plain(getattr(args, k)) for k in _actions(leaf) if hasattr(args, k)}


def write_resolved(args: argparse.Namespace) -> Path | None:
    """The resolved options into `<out>/options.yaml` where the run made a folder `out`, or beside a
    file it made as `<out>.options.yaml`; None where the command names no output."""
    out = getattr(args, "out", None)
    if getattr(args, "_parser", None) is None or not out or not Path(out).exists():
        return None
    path = Path(out) / OPTIONS_FILE if Path(out).is_dir() else Path(f"{out}.{OPTIONS_FILE}")
    path.write_text(
        f"# l3e {args._parser.prog.removeprefix('l3e ')} --config {path.name}\n"
        + yaml.safe_dump(resolved_options(args), sort_keys=False)
    )
    return path
