"""Competing load for the benchmarks: N processes that each spin a core, started and stopped by the
benchmark, so that a figure can be read idle and beside the work a robot's computer always has.

`spinning(n)` holds the load for a block; `loads(text)` parses the usual `--loads 0,4`; `ratio_row`
formats one row of figures by load with the loaded-over-idle ratios.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Iterator
from contextlib import contextmanager


def _spin() -> None:
    while True:
        pass


@contextmanager
def spinning(processes: int, settle: float = 1.0) -> Iterator[None]:
    """`processes` spinning processes for the block (none for 0), `settle` seconds after they start."""
    spinners = [mp.get_context("spawn").Process(target=_spin, daemon=True) for _ in range(processes)]
    for process in spinners:
        process.start()
    if spinners:
        time.sleep(settle)
    try:
        yield
    finally:
        for process in spinners:
            process.terminate()
        for process in spinners:
            process.join()


def loads(text: str) -> list[int]:
    """'0,2,4' -> [0, 2, 4]; the first is the reference the ratios divide by."""
    values = [int(part) for part in text.split(",") if part.strip()]
    if not values or min(values) < 0:
        raise SystemExit(f"--loads takes numbers of spinning processes such as 0,4, not {text!r}")
    return values


def ratio_row(name: str, by_load: dict[int, float], unit: str = "ms", width: int = 34) -> str:
    """'name  v0 v1 ... (x1/x0 ...)' in the order of the loads."""
    order = list(by_load)
    base = by_load[order[0]]
    figures = "".join(f"{by_load[n]:10.1f}" for n in order)
    ratios = " ".join(f"x{n}/x{order[0]} {by_load[n] / base:.2f}" for n in order[1:])
    return f"{name:{width}s}{figures} {unit}  {ratios}"


def header(load_list: list[int], width: int = 34) -> str:
    return f"{'':{width}s}" + "".join(f"{f'load {n}':>10s}" for n in load_list)
