"""The helper processes of jaxcart.workers: the same results as in-process, in order, whatever
a helper does (fails, cannot import the function, dies); owned by their caller, who closes them
(no process left); one map at a time across threads; a clear error for a bad setting."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from jaxcart import workers
from jaxcart.errors import UserError
from jaxcart.workers import SERIAL, Helpers


def slow_square(x):
    """Work long enough (a few ms) that both processes take a share."""
    s = 0.0
    for i in range(20000):
        s += math.sin(i * 1e-3)
    return x * x + 0.0 * s


def fails_on_three(x):
    if x == 3:
        raise ValueError("three")
    return x


def pid_of_helper(_x):
    return os.getpid()


def _ready(helpers: Helpers) -> Helpers:
    """Wait until every helper has imported (a map would otherwise run here alone), however
    long a busy machine takes: until each has said ready, or has died."""
    import time

    helpers.start()
    while not all(h.is_ready() or not h.alive for h in helpers._procs):
        time.sleep(0.05)
    assert all(h.ready for h in helpers._procs), "a helper process died while importing"
    return helpers


@pytest.fixture
def two_helpers():
    with Helpers(2) as helpers:
        yield _ready(helpers)


def test_results_in_order_and_the_work_shared(two_helpers):
    items = list(range(30))
    assert two_helpers.map(slow_square, items) == [x * x for x in items]
    pids = set(two_helpers.map(pid_of_helper, range(12)))
    assert os.getpid() in pids and len(pids) == 3  # this process and both helpers


def test_an_exception_is_raised_here_as_the_function_raises_it(two_helpers):
    with pytest.raises(ValueError, match="three"):
        two_helpers.map(fails_on_three, range(8))
    assert two_helpers.map(fails_on_three, [0, 1, 2, 4]) == [0, 1, 2, 4]


def test_a_function_a_helper_cannot_import_is_computed_here(two_helpers):
    local = lambda x: 2 * x  # noqa: E731 - not importable by name in a helper
    assert two_helpers.map(local, range(6)) == [0, 2, 4, 6, 8, 10]


def test_a_dead_helper_costs_only_speed(two_helpers):
    for h in two_helpers._procs:
        h.proc.kill()
        h.proc.wait()
    assert two_helpers.map(slow_square, range(10)) == [x * x for x in range(10)]


def test_shares_of_equal_weight():
    weights = [5000, 3000, 10000, 8000, 6000, 2500] * 3
    mine, theirs = workers._deal(weights, 2)
    loads = [sum(weights[i] for i in s) for s in (mine, theirs)]
    assert sorted(mine + theirs) == list(range(len(weights)))
    assert abs(loads[0] - loads[1]) <= max(weights)


def _children() -> set[int]:
    """This process's child processes (Linux: /proc)."""
    found = set()
    for path in Path(f"/proc/{os.getpid()}/task").glob("*/children"):
        found |= {int(pid) for pid in path.read_text().split()}
    return found


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc")
def test_the_caller_owns_the_helpers_and_none_outlives_it():
    """Nothing starts on its own (no module-wide pool, no environment variable decides): the
    helpers start with their owner's block and are gone, waited for, when it ends."""
    before = _children()
    with Helpers(2) as helpers:
        assert len(_children() - before) == 2
        assert _ready(helpers).map(slow_square, range(8)) == [x * x for x in range(8)]
    assert _children() == before
    assert not hasattr(workers, "_pool") and not hasattr(workers, "VARIABLE")


def test_no_helpers_and_the_serial_executor_compute_here():
    with Helpers(0) as none:
        assert none.map(pid_of_helper, range(3)) == [os.getpid()] * 3
    assert SERIAL.map(slow_square, [1, 2], [5.0, 1.0]) == [1, 4]
    assert workers.default_count() == min(max(len(os.sched_getaffinity(0)) - 1, 0), workers.MOST)


def test_two_threads_share_the_helpers_one_map_at_a_time(two_helpers):
    """The lab's diagnosis and its parts map from two threads: each map gets the helpers in
    its turn (neither falls back to running alone unseen), and both get their own results."""
    import concurrent.futures

    with concurrent.futures.ThreadPoolExecutor(2) as threads:
        a = threads.submit(two_helpers.map, slow_square, range(20))
        b = threads.submit(two_helpers.map, pid_of_helper, range(12))
        assert a.result() == [x * x for x in range(20)]
        assert len(set(b.result())) == 3  # this process and both helpers took a share


def test_a_bad_helpers_option_is_a_user_error():
    from types import SimpleNamespace

    from tuning.commands.options import helpers

    with pytest.raises(UserError, match="--helpers -1: give a whole number"):
        helpers(SimpleNamespace(helpers=-1))
    assert helpers(SimpleNamespace(helpers=3)).count == 3
    assert helpers(SimpleNamespace(helpers=3), distributed=True).count == 0


def test_an_exact_run_in_a_helper_is_the_same_float_for_float(two_helpers):
    """A float64 plant sent to a helper is simulated in float64 there: the same positions."""
    import jax

    import jaxcart as jc
    from jaxcart.plantspec import build_plant
    from tuning.estimation.engine.exact_runs import exact_position

    with jax.enable_x64(True):
        plant = build_plant({"B_eq": 4.6, "f_c": 0.45, "v_sat": 5.0}, where="the test")
        steps = [(plant, jc.PID(kp=k), jc.step(0.3, horizon=1.0)) for k in (10.0, 30.0, 50.0, 80.0)]
        jobs = [(*job, False) for job in steps]
        here = [exact_position(j) for j in jobs]
        spread = two_helpers.map(exact_position, jobs)
    assert all(np.array_equal(a, b) for a, b in zip(here, spread, strict=True))
