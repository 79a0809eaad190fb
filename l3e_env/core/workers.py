"""Ordered work in worker processes (`process_context`). The slow judges (maps, the scan estimate in a replay,
`l3e judge`) each build one heavy object (a detector, a LiDAR on its own copy of a scene) that
cannot cross a process boundary; every worker builds its own once from picklable settings, and
the results come back in the order of the jobs, so a run gives the same output with any number
of workers."""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sized
from itertools import chain, islice
from multiprocessing.context import ForkServerContext, SpawnContext
from typing import Any, TypeVar

from l3e_env.core.threads import one_thread_per_part

Job = TypeVar("Job")
Result = TypeVar("Result")

_worker: tuple[Callable[[Any, Any], Any], Any] | None = None  # this worker's (work, object)


def die_with_parent() -> None:
    """A worker process's initializer: on Linux, the kernel ends the worker when the process that started
    it dies, so a killed run leaves no idle workers behind (elsewhere it does nothing). A worker whose
    run died while it started (its parent then was already gone, or is the fork server about to go)
    ends here. Hand-written: multiprocessing has no such option, and prctl is one call."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    run = multiprocessing.parent_process()  # the run that asked for this worker (None: not a worker)
    if run is not None and not run.is_alive():
        os._exit(1)


def worker_start() -> None:
    """A pool worker's initializer: it dies with its parent (die_with_parent) and runs each part of
    a step on one thread, as the other workers fill the other cores (threads.one_thread_per_part)."""
    die_with_parent()
    one_thread_per_part()


def process_context(preload: Iterable[str] = ()) -> SpawnContext | ForkServerContext:
    """Where the project's worker processes come from: forked from one server process
    (multiprocessing's forkserver, started with the first pool) that has imported the modules
    `preload` names (those of the first pool's work), where the platform has it; elsewhere each
    spawned as a new interpreter. Either way from a clean process, never a fork of this one, whose
    threads (Embree's, torch's) a fork would copy mid-work; a forked worker starts without importing
    the libraries again, as a spawned one must."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    # read when the server starts, once; the first dies with this process (core.forkserver)
    context.set_forkserver_preload(["l3e_env.core.forkserver", *preload])
    return context


def _one_torch_thread() -> None:
    """The workers share the cores: torch, where the work has imported it, runs on one thread. It is
    looked up rather than imported, so that workers of torch-free work never load it."""
    if (torch := sys.modules.get("torch")) is not None:
        torch.set_num_threads(1)


def _start(work: Callable[[Any, Any], Any], build: Callable[..., Any], args: tuple) -> None:
    global _worker
    worker_start()
    _one_torch_thread()
    obj = build(*args)
    _one_torch_thread()  # `build` may have imported it (a learned detector)
    _worker = work, obj


def _run(job: Any) -> Any:
    assert _worker is not None, "a worker's object is made by its initializer"
    work, obj = _worker
    return work(obj, job)


def ordered_map(
    work: Callable[[Any, Job], Result],
    jobs: Iterable[Job],
    local: Any,
    build: Callable[..., Any],
    args: tuple,
    workers: int = 1,
) -> Iterator[Result]:
    """work(obj, job) for each job, in order. With one worker (or one job) `obj` is the caller's
    `local`, or `build(*args)` made here when `local` is None (a caller that does not hold one);
    with more, each of `workers` processes (`process_context`) uses its own `build(*args)`. `work`
    and `build` must be module-level functions, `args` picklable. Jobs are drawn from `jobs` as
    workers free up (a few ahead), so a long stream (a bag's scans) is never held whole."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if isinstance(jobs, Sized):
        workers = min(workers, max(1, len(jobs)))
    jobs = iter(jobs)
    head = list(islice(jobs, 2))
    if workers == 1 or len(head) < 2:
        if local is None and head:
            local = build(*args)
        for job in chain(head, jobs):
            yield work(local, job)
        return
    context = process_context(dict.fromkeys([work.__module__, build.__module__]))
    with context.Pool(workers, _start, (work, build, args)) as pool:
        pending: deque = deque()
        for job in chain(head, jobs):
            pending.append(pool.apply_async(_run, (job,)))
            if len(pending) >= 2 * workers:
                yield pending.popleft().get()
        while pending:
            yield pending.popleft().get()
