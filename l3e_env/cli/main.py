"""The `l3e` command line: a thin layer over library functions that return results. Each command
group's module adds its parsers (`register`) and handlers."""

from __future__ import annotations

import argparse
import sys
import warnings
from importlib.metadata import entry_points, version

from . import data, drive, model, scans
from .option_files import add_option_files, resolve, write_resolved


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="l3e", description="Learned LiDAR localizability in simulation (L3E).")
    parser.add_argument("--version", action="version", version=f"l3e {version('l3e')}")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in (drive, data, model, scans):
        group.register(sub)
    # packages built on l3e_env (policies: `l3e policy`) add their commands through this entry-point
    # group, so that l3e_env never imports them
    for entry in entry_points(group="l3e.commands"):
        entry.load()(sub)
    add_option_files(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = resolve(build_parser(), argv)

    def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
        # a library's warning as a line of the command's own, not Python's with its source line
        print(f"l3e {args.command}: warning: {message}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show_warning
            status = int(args.func(args))
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"l3e {args.command}: error: {exc}", file=sys.stderr)
        return 2
    if status == 0 and (written := write_resolved(args)) is not None:
        print(f"options: {written} ({args._parser.prog} ... --config {written} runs it again)")
    return status


if __name__ == "__main__":
    sys.exit(main())
