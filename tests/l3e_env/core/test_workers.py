"""ordered_map: the same results in the same order from worker processes as from the caller."""

import operator
import os

import pytest

from l3e_env.core.workers import ordered_map


def test_workers_give_the_serial_results_in_order():
    jobs = list(range(12))
    serial = list(ordered_map(operator.mul, jobs, 3, int, ("3",), workers=1))
    assert serial == [3 * j for j in jobs]
    assert list(ordered_map(operator.mul, jobs, 3, int, ("3",), workers=2)) == serial
    # the workers build their own object: a local one that differs shows which path ran
    assert list(ordered_map(operator.mul, jobs, 5, int, ("3",), workers=2)) == serial
    assert list(ordered_map(operator.mul, [4], 5, int, ("3",), workers=2)) == [20]  # one job stays local
    assert list(ordered_map(operator.mul, [4], None, int, ("3",), workers=2)) == [12]  # built here when none is held
    # a stream (a bag's scans) is drawn as the workers free up, in the same order
    assert list(ordered_map(operator.mul, (j for j in jobs), 5, int, ("3",), workers=2)) == serial


def test_one_worker_runs_in_the_caller_and_zero_is_refused():
    pids = set(ordered_map(lambda _, job: os.getpid(), range(3), None, int, (), workers=1))
    assert pids == {os.getpid()}
    with pytest.raises(ValueError, match="workers must be at least 1"):
        list(ordered_map(operator.mul, [1], 1, int, (), workers=0))


def test_a_killed_run_leaves_no_worker_behind(tmp_path):
    """A real SIGKILL to the process that started the workers: the kernel ends them (die_with_parent)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    script = tmp_path / "run.py"
    script.write_text(
        "import os, sys, time\n"
        "from l3e_env.core.workers import process_context, worker_start\n"
        "def pid(_):\n"
        "    return os.getpid()\n"
        "def nap(_):\n"
        "    time.sleep(60)\n"
        "if __name__ == '__main__':\n"
        "    with process_context().Pool(2, worker_start) as pool:\n"
        "        pids = set(pool.map(pid, range(8)))\n"
        "        print(' '.join(map(str, pids)), flush=True)\n"
        "        list(pool.map(nap, range(2)))\n"
    )
    run = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    workers = [int(p) for p in run.stdout.readline().split()]
    assert workers and all(Path(f"/proc/{p}").exists() for p in workers)
    os.kill(run.pid, signal.SIGKILL)
    run.wait(timeout=10)
    # every process of the run: the workers that took a job, any other, and the fork server they came
    # from (their command lines carry the run's folder)
    deadline = time.monotonic() + 20  # a loaded machine
    while time.monotonic() < deadline and any(_alive(p) for p in [*workers, *_started_in(tmp_path)]):
        time.sleep(0.1)
    assert not any(_alive(p) for p in workers) and not [p for p in _started_in(tmp_path) if _alive(p)]


def _started_in(folder) -> list[int]:
    """The processes whose command line names `folder`."""
    from pathlib import Path

    found = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and str(folder) in (proc / "cmdline").read_bytes().decode(errors="replace"):
                found.append(int(proc.name))
        except OSError:
            continue
    return found


def _alive(pid: int) -> bool:
    """Running, not a zombie waiting for its parent to collect it."""
    from pathlib import Path

    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except OSError:
        return False
    return state != "Z"
