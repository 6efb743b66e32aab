"""The engine's Gauss-Newton on exact residuals (tuning/estimation/engine/exact_polish.py): a
known optimum on the exact simulator, the bounds, and the forward differences it takes."""

import dataclasses

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.exact import simulate_exact
from tuning.estimation.engine.exact_polish import gauss_newton, jacobian

TRUTH = np.log([1.5, 0.44])  # log B_eq [N s/m], log f_c [N]
EXPERIMENT = jc.tap(1.0, horizon=0.6)


def _position(x):
    b_eq, f_c = np.exp(x)
    plant = jc.tap_plant(B_eq=float(b_eq), effects=(jc.Coulomb(f_c=float(f_c)),))
    return np.asarray(simulate_exact(plant, None, EXPERIMENT).position, dtype=float)


@pytest.fixture(scope="module")
def residual():
    target = _position(TRUTH)  # noise-free: the optimum is the truth, residual 0
    return lambda x: _position(x) - target


WIDE = (np.full(2, -10.0), np.full(2, 10.0))


def _each(residual):
    """The engine's contract from a residual of one point: points -> their residuals."""
    return lambda xs: [residual(x) for x in xs]


def test_gauss_newton_finds_a_known_optimum_on_the_exact_simulator(residual):
    """From B_eq and f_c 20 % off, the polish returns the values the data were made with (to
    1e-6 relative), says it improved and converged, and its Jacobian is the one at the values
    returned."""
    start = np.log([1.8, 0.35])
    done = gauss_newton(_each(residual), start, np.full(2, 1e-6), WIDE, 20)
    assert done.improved and done.converged and done.iterations < 20
    assert np.exp(done.x) == pytest.approx(np.exp(TRUTH), rel=1e-6)
    assert np.sqrt(np.mean(done.r**2)) < 1e-9  # [m]
    fresh = jacobian(_each(residual), done.x, residual(done.x), np.full(2, 1e-6))
    np.testing.assert_array_equal(done.jac, fresh)


def test_gauss_newton_stays_inside_its_bounds(residual):
    """An upper bound on f_c below the truth: the polish ends on it (within a step's clip),
    never beyond, and B_eq takes up what it can."""
    high = np.array([10.0, np.log(0.4)])
    done = gauss_newton(_each(residual), np.log([1.8, 0.35]), np.full(2, 1e-6), (WIDE[0], high), 20)
    assert done.improved
    assert done.x[1] <= high[1] and np.exp(done.x[1]) == pytest.approx(0.4, rel=1e-9)


def test_forward_differences_agree_with_central_ones(residual):
    """At the optimum the forward-difference Jacobian (step 1e-6 in the logs) equals the
    central one within 1e-5 of each column's norm: the central's second exact run per
    parameter buys nothing measurable (the fit's values moved by 3e-5 standard errors)."""
    h = 1e-6
    fwd = jacobian(_each(residual), TRUTH, residual(TRUTH), np.full(2, h))
    central = np.column_stack(
        [(residual(TRUTH + h * e) - residual(TRUTH - h * e)) / (2 * h) for e in np.eye(2)]
    )
    error = np.linalg.norm(fwd - central, axis=0) / np.linalg.norm(central, axis=0)
    assert np.all(error < 1e-5)


def test_no_descent_keeps_the_start():
    """A start at the minimum (a residual linear in x with a part no x explains): no step
    lowers the cost; the start is kept with its Jacobian, and not counted as an improvement."""

    def residual(x):
        return np.array([x[0] - 1.0, x[1] + 2.0, 0.5])

    start = np.array([1.0, -2.0])
    done = gauss_newton(_each(residual), start, np.full(2, 1e-6), WIDE, 5)
    assert not done.improved and done.converged and done.iterations == 1
    np.testing.assert_array_equal(done.x, start)
    np.testing.assert_allclose(done.jac, [[1, 0], [0, 1], [0, 0]], atol=1e-6)


def test_a_fit_that_cannot_reach_its_target_stops_after_the_first_jacobian():
    """A residual linear in x with 0.5 m that no x explains: its least cost is 0.25 m^2.
    With a target below that the fit stops at the start after one Jacobian (not improved, not
    converged); with a target above it, it fits to the minimum as without one."""

    def residual(x):
        return np.array([x[0] - 1.0, x[1] + 2.0, 0.5])

    start = np.array([3.0, 1.0])
    hopeless = gauss_newton(_each(residual), start, np.full(2, 1e-6), WIDE, 5, target=0.2)
    assert not hopeless.improved and not hopeless.converged and hopeless.iterations == 0
    np.testing.assert_array_equal(hopeless.x, start)
    assert hopeless.jac is not None
    reached = gauss_newton(_each(residual), start, np.full(2, 1e-6), WIDE, 5, target=0.3)
    np.testing.assert_allclose(reached.x, [1.0, -2.0], atol=1e-6)


def test_a_fits_exact_runs_move_only_the_recordings_a_value_moves():
    """fit()'s exact runs go through the engine's memo (engine/exact_runs.ExactMemo): a point
    that moves one recording's start re-simulates that recording alone, a shared value moves
    both, and each run equals the exact simulator's own, bit for bit."""
    from jaxcart.synthetic import make_recording
    from tuning.estimation.engine.exact_runs import exact_position
    from tuning.estimation.fit import FitSettings, fit_segment
    from tuning.estimation.fitting.model import _Problem

    plant = jc.Plant(effects=(jc.Coulomb(f_c=0.4),))
    recs = [
        make_recording(plant, jc.PID(kp=50.0), jc.step(0.1 * k, horizon=0.4), seed=k)
        for k in (1, 2)
    ]
    settings = FitSettings()
    segments = [fit_segment(r, ("B_eq",), {}, settings) for r in recs]
    problem = _Problem(segments, ("B_eq",), settings)
    theta = problem.theta0
    (first,) = problem.simulate_exact_many([theta])
    assert problem.memo.made == 2
    start = problem.entries.index("y0@1")
    moved, shared = theta.copy(), theta.copy()
    moved[start] += 0.5
    shared[0] += 1e-3
    (again, one) = problem.simulate_exact_many([theta, moved])
    assert problem.memo.made == 3 and one[0] is first[0] and again[1] is first[1]
    problem.simulate_exact_many([shared])
    assert problem.memo.made == 5
    for k, seg in enumerate(segments):
        values, nuisance = problem.segment_values(moved, k)
        exp = dataclasses.replace(seg.experiment, **nuisance)
        job = (seg.plant.replace(**values), seg.controller, exp, seg.counts_in_loop)
        np.testing.assert_array_equal(one[k], exact_position(job))
