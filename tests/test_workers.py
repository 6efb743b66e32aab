"""The helper processes of jaxcart.workers: the same results as in-process, in order, whatever
a helper does (fails, cannot import the function, dies); a clear error for a bad setting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxcart import workers
from jaxcart.errors import UserError


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
    import os

    return os.getpid()


@pytest.fixture
def two_helpers(monkeypatch):
    monkeypatch.setenv(workers.VARIABLE, "2")
    workers.start()
    # Wait until both have imported (the first map would otherwise run here alone), however
    # long a busy machine takes: until each has said ready, or has died.
    import time

    helpers = workers._helpers()
    while not all(h.is_ready() or not h.alive for h in helpers):
        time.sleep(0.05)
    assert all(h.ready for h in helpers), "a helper process died while importing"
    yield
    workers.shutdown()


def test_results_in_order_and_the_work_shared(two_helpers):
    import os

    items = list(range(30))
    assert workers.map(slow_square, items) == [x * x for x in items]
    pids = set(workers.map(pid_of_helper, range(12)))
    assert os.getpid() in pids and len(pids) == 3  # this process and both helpers


def test_an_exception_is_raised_here_as_the_function_raises_it(two_helpers):
    with pytest.raises(ValueError, match="three"):
        workers.map(fails_on_three, range(8))
    assert workers.map(fails_on_three, [0, 1, 2, 4]) == [0, 1, 2, 4]


def test_a_function_a_helper_cannot_import_is_computed_here(two_helpers):
    local = lambda x: 2 * x  # noqa: E731 - not importable by name in a helper
    assert workers.map(local, range(6)) == [0, 2, 4, 6, 8, 10]


def test_a_dead_helper_costs_only_speed(two_helpers):
    for h in workers._helpers():
        h.proc.kill()
        h.proc.wait()
    assert workers.map(slow_square, range(10)) == [x * x for x in range(10)]


def test_shares_of_equal_weight():
    weights = [5000, 3000, 10000, 8000, 6000, 2500] * 3
    mine, theirs = workers._deal(weights, 2)
    loads = [sum(weights[i] for i in s) for s in (mine, theirs)]
    assert sorted(mine + theirs) == list(range(len(weights)))
    assert abs(loads[0] - loads[1]) <= max(weights)


def test_the_setting(monkeypatch):
    monkeypatch.setenv(workers.VARIABLE, "0")
    assert workers.count() == 0
    assert workers.map(slow_square, [1, 2]) == [1, 4]
    monkeypatch.setenv(workers.VARIABLE, "two")
    with pytest.raises(UserError, match="JAXCART_WORKERS='two'.*whole number"):
        workers.count()


def test_an_exact_run_in_a_helper_is_the_same_float_for_float(two_helpers):
    """A float64 plant sent to a helper is simulated in float64 there: the same positions."""
    import jax

    import jaxcart as jc
    from jaxcart.plantspec import build_plant
    from tuning.estimation.engine.exact_runs import exact_position

    with jax.enable_x64(True):
        plant = build_plant({"B_eq": 4.6, "f_c": 0.45, "v_sat": 5.0}, where="the test")
        jobs = [(plant, jc.PID(kp=k), jc.step(0.3, horizon=1.0)) for k in (10.0, 30.0, 50.0, 80.0)]
        here = [exact_position(j) for j in jobs]
        spread = workers.map(exact_position, jobs)
    assert all(np.array_equal(a, b) for a, b in zip(here, spread, strict=True))
