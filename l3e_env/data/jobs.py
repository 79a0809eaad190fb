"""Independent jobs spread over worker processes, locally or as Ray tasks (a cluster): the pool that
labels a dataset's shards and drives the families benchmark."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

from l3e_env.core.workers import process_context, worker_start

Result = TypeVar("Result")
JOB_BACKENDS = ("local", "ray")


def run_jobs(
    work: Callable[[Any, Any], Result],
    config: Any,
    todo: list,
    workers: int,
    backend: str = "local",
    ray_address: str | None = None,
) -> Iterator[Result]:
    """`work(config, job)` for each job of `todo`, results as they finish (not in order): in this
    process (one worker or one job), in `workers` local processes, or as Ray tasks ("ray", on a local
    Ray instance or the cluster at `ray_address`). `work` is a module-level function and `config` and
    the jobs picklable; each job's result must not depend on where it ran."""
    if backend not in JOB_BACKENDS:
        raise ValueError(f"unknown backend '{backend}' ({', '.join(JOB_BACKENDS)})")
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if backend == "ray":
        from .ray_backend import run_with_ray

        yield from run_with_ray(work, config, todo, workers, ray_address)
    elif workers <= 1 or len(todo) <= 1:
        for job in todo:
            yield work(config, job)
    else:
        context = process_context([work.__module__])
        with ProcessPoolExecutor(min(workers, len(todo)), context, worker_start) as pool:  # no idle workers
            futures = [pool.submit(work, config, job) for job in todo]
            for fut in as_completed(futures):
                yield fut.result()
