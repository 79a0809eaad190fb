"""Threads that share a busy machine. A robot's computer runs SLAM, planners and drivers beside the
detector, and a thread that spins while it waits for its team steals the core another process needs:
OpenMP's default wait policy and OpenBLAS's threads both spin.

- Importing `l3e_env` sets `OMP_WAIT_POLICY=PASSIVE` unless it is set: OpenMP threads (torch's,
  small_gicp's) sleep when idle. An OpenMP runtime reads it once, when it loads, so a script that
  imports torch before `l3e_env` keeps torch's default; set it in the environment to be sure.
- `settle_process_threads()`: for processes the project owns (the `l3e` command, its workers): the
  same, and numpy's BLAS on one thread, unless the user set either; before numpy and torch load.
  Library users set the same variables themselves (`OMP_WAIT_POLICY=PASSIVE OPENBLAS_NUM_THREADS=1`).
- `one_blas_thread()`: the few large products the project makes itself (the LiDAR's ray directions)
  on one BLAS thread in any process, without touching the process's own setting.
- `part_threads()`: the threads one part of a step (a scan's rays, the ICP target's normals) splits
  its work over: up to 2, this project's reference machine, or `L3E_PART_THREADS`. A worker among
  others (`one_thread_per_part()`, which the project's worker pools call) uses one: there the other
  workers fill the cores, and a second thread only adds its hand-over to every part's cost.
The classifier runs each scan on one torch thread (`Classifier.predict`), so it has no team to wait for.
"""

from __future__ import annotations

import os
from contextlib import AbstractContextManager, nullcontext
from typing import Any

PACKAGE_THREAD_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}
PROCESS_THREAD_ENV = {**PACKAGE_THREAD_ENV, "OPENBLAS_NUM_THREADS": "1"}
PART_THREADS_ENV = "L3E_PART_THREADS"

_blas: Any = None  # threadpoolctl's handle on the loaded BLAS libraries, found once


def settle_process_threads(variables: dict[str, str] = PROCESS_THREAD_ENV) -> None:
    """Set `variables` where the user has not; child processes inherit them."""
    for name, value in variables.items():
        os.environ.setdefault(name, value)


def part_threads() -> int:
    """Threads for one part of a step: `L3E_PART_THREADS` where set, else up to 2 (see the module)."""
    value = os.environ.get(PART_THREADS_ENV)
    if value is None:
        return min(2, os.cpu_count() or 1)
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{PART_THREADS_ENV} must be a whole number of threads, at least 1, not {value!r}")
    return int(value)


def one_thread_per_part() -> None:
    """This process is one worker of several: each part of a step on one thread (part_threads)."""
    os.environ[PART_THREADS_ENV] = "1"


def one_blas_thread() -> AbstractContextManager:
    """A block whose BLAS calls run on one thread (about 30 microseconds to enter and leave)."""
    global _blas
    if _blas is None:
        from threadpoolctl import ThreadpoolController

        _blas = ThreadpoolController().select(user_api="blas")
    return _blas.limit(limits=1) if _blas.lib_controllers else nullcontext()
