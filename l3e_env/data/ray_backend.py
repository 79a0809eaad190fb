"""Run dataset shards as Ray tasks, on a local Ray instance or a cluster (optional extra `cluster`).

The jobs, seeds and shard files are those of the local backend, so both give identical data.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from typing import Any


def run_with_ray(
    run_shard: Callable[[Any, Any], Any], config: Any, todo: list, workers: int, address: str | None
) -> Iterator[Any]:
    """`run_shard(config, shard)` for each shard of `todo` as Ray tasks, results as they finish (the local
    backend's function is passed in, so that this module needs nothing of the dataset's)."""
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise RuntimeError("the ray backend needs Ray: pip install -e '.[cluster]'") from exc
    started_here, made_tmp = not ray.is_initialized(), None
    if started_here:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            # Ray writes under the home folder and /tmp unless told otherwise
            # (a short path: Ray's socket names must fit in 107 bytes)
            tmp = os.environ.get("L3E_RAY_TMPDIR") or (made_tmp := tempfile.mkdtemp(prefix="l3e-ray-"))
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, _temp_dir=tmp)
    try:
        task = ray.remote(num_cpus=1)(run_shard)
        pending = [task.remote(config, shard) for shard in todo]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            yield ray.get(ready[0])
    finally:
        if started_here:
            ray.shutdown()
        if made_tmp:
            shutil.rmtree(made_tmp, ignore_errors=True)
