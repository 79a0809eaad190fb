import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from l3e_env.core import threads
from l3e_env.core.threads import PROCESS_THREAD_ENV, one_blas_thread


def _environment_after(code: str, **env: str) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in PROCESS_THREAD_ENV} | env
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=clean).stdout


def test_the_package_makes_openmp_threads_sleep_unless_the_user_chose():
    show = "import os, l3e_env; print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('OPENBLAS_NUM_THREADS'))"
    assert _environment_after(show).split() == ["PASSIVE", "None"]  # a library leaves numpy's BLAS alone
    assert _environment_after(show, OMP_WAIT_POLICY="ACTIVE").split() == ["ACTIVE", "None"]


def test_the_command_also_gives_numpy_one_blas_thread_before_numpy_loads():
    code = (
        "import sys; import l3e_env.cli; assert 'numpy' not in sys.modules\n"
        "import os; print(os.environ['OMP_WAIT_POLICY'], os.environ['OPENBLAS_NUM_THREADS'])"
    )
    assert _environment_after(code).split() == ["PASSIVE", "1"]
    assert _environment_after(code, OPENBLAS_NUM_THREADS="2").split() == ["PASSIVE", "2"]


def test_one_blas_thread_holds_for_the_block_only():
    from threadpoolctl import threadpool_info

    def blas_threads() -> list[int]:
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    before = blas_threads()
    with one_blas_thread():
        inside = blas_threads()
        product = np.ones((1000, 3)) @ np.eye(3)
    assert inside and all(n == 1 for n in inside) and blas_threads() == before
    assert np.array_equal(product, np.ones((1000, 3)))


def test_a_part_of_a_step_uses_up_to_two_threads_and_a_worker_one(monkeypatch):
    monkeypatch.setenv(threads.PART_THREADS_ENV, "3")  # restored to the session's own afterwards
    assert threads.part_threads() == 3
    monkeypatch.delenv(threads.PART_THREADS_ENV)
    assert threads.part_threads() == min(2, os.cpu_count() or 1)
    threads.one_thread_per_part()
    assert threads.part_threads() == 1
    from l3e_env.sim.raycast import EmbreeCaster

    assert EmbreeCaster(trimesh.creation.box()).threads == 1


def test_a_part_thread_count_that_is_not_a_whole_number_is_refused(monkeypatch):
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv(threads.PART_THREADS_ENV, bad)
        with pytest.raises(ValueError, match="L3E_PART_THREADS"):
            threads.part_threads()
