"""ordered_map: the same results in the same order from spawned workers as from the caller."""
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
