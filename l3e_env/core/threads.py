"""Threads that share a busy machine. A robot's computer runs SLAM, planners and drivers beside the
detector, and a thread that spins while it waits for its team steals the core another process needs:
OpenMP's default wait policy and OpenBLAS's threads both spin.

- `settle_process_threads()`: for processes the project owns (the `l3e` command, its workers): OpenMP
  threads sleep when idle and numpy's BLAS runs on one thread, unless the user set either; it must
  run before torch and numpy load. Library users set the same variables themselves
  (`OMP_WAIT_POLICY=PASSIVE OPENBLAS_NUM_THREADS=1`), see docs/speed.md.
- `one_blas_thread()`: the few large products the project makes itself (the LiDAR's ray directions)
  on one BLAS thread in any process, without touching the process's own setting.
The classifier runs each scan on one torch thread (`Classifier.predict`), so it has no team to wait for.
"""
from __future__ import annotations

import os
from contextlib import AbstractContextManager, nullcontext
from typing import Any

PROCESS_THREAD_ENV = {"OMP_WAIT_POLICY": "PASSIVE", "OPENBLAS_NUM_THREADS": "1"}

_blas: Any = None  # threadpoolctl's handle on the loaded BLAS libraries, found once


def settle_process_threads() -> None:
    """Set PROCESS_THREAD_ENV where the user has not; children inherit it."""
    for name, value in PROCESS_THREAD_ENV.items():
        os.environ.setdefault(name, value)


def one_blas_thread() -> AbstractContextManager:
    """A block whose BLAS calls run on one thread (about 30 microseconds to enter and leave)."""
    global _blas
    if _blas is None:
        from threadpoolctl import ThreadpoolController

        _blas = ThreadpoolController().select(user_api="blas")
    return _blas.limit(limits=1) if _blas.lib_controllers else nullcontext()
