"""The engine's least-squares solvers share one contract (engine/least_squares.py): each
of them, driven by the same host loop, reaches scipy's least-squares solution of a small
nonlinear problem."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares

from tuning.estimation.engine.least_squares import (
    LM_DAMPING,
    State,
    compiled_marquardt,
    levenberg_marquardt,
    line_search,
    minimize,
)

T = np.linspace(0.0, 2.0, 60)
TRUTH = np.array([0.8, 1.7, 0.3])  # a * exp(-b t) + c, with a little deterministic noise
Y = TRUTH[0] * np.exp(-TRUTH[1] * T) + TRUTH[2] + 1e-3 * np.sin(37.0 * T)
START = np.array([0.3, 0.5, 0.0])


def _residual(x):
    return x[0] * np.exp(-x[1] * T) + x[2] - Y


def _jacobian(x):
    e = np.exp(-x[1] * T)
    return np.column_stack([e, -x[0] * T * e, np.ones_like(T)])


def _evaluate(xs):
    return np.stack([_residual(x) for x in xs]), np.stack([_jacobian(x) for x in xs])


@pytest.fixture(scope="module")
def reference():
    return least_squares(_residual, START, jac=_jacobian, xtol=1e-14, ftol=1e-14).x


def _lm_host():
    return levenberg_marquardt(
        dampings=LM_DAMPING, shrink=5.0, damping_range=(1e-12, 1e10), give_up=True, max_step=1.0
    )


@pytest.mark.parametrize("kind", ["levenberg_marquardt", "line_search"])
def test_one_driver_takes_every_solver(kind, reference):
    solver = _lm_host() if kind == "levenberg_marquardt" else line_search(tolerance=1e-6)
    r0 = _residual(START)
    state = minimize(
        solver,
        _evaluate if kind == "levenberg_marquardt" else lambda xs: (_evaluate(xs)[0], None),
        solver.init(START, r0, _jacobian(START)),
        100,
        jacobian=lambda x, r: _jacobian(x),
    )
    assert state.converged
    np.testing.assert_allclose(state.x, reference, rtol=1e-7)
    assert state.cost < float(r0 @ r0)


def test_a_held_entry_stays_and_the_rest_fit_as_alone():
    """``free``: a held entry does not move; the others reach the fit with it fixed."""
    held = np.array([1.0, 1.0, 0.0])
    solver = levenberg_marquardt(
        dampings=LM_DAMPING, give_up=True, damping_range=(1e-12, 1e10), free=held
    )
    start = np.array([0.3, 0.5, 0.25])
    state = minimize(solver, _evaluate, solver.init(start, _residual(start), _jacobian(start)), 200)
    alone = least_squares(lambda ab: _residual(np.r_[ab, 0.25]), start[:2], xtol=1e-14).x
    assert state.x[2] == 0.25
    np.testing.assert_allclose(state.x[:2], alone, rtol=1e-6)


def test_the_compiled_solver_is_driven_alike_and_runs_inside_a_compiled_step(reference):
    """compiled_marquardt (a diagnosis's batch runs its ask and tell inside one jitted,
    vmapped step): the host loop drives it to scipy's solution, and in the diagnosis's form,
    from a state without a residual (cost inf: its own point first), one jitted step at a time
    over two starts at once, it reaches the same point (float64 both)."""
    bounds = (jnp.full(3, -10.0), jnp.full(3, 10.0))
    with jax.enable_x64(True):
        solver = compiled_marquardt(bounds=bounds, free=jnp.ones(3))
        r0 = _residual(START)
        state = minimize(solver, _evaluate, solver.init(START, r0, _jacobian(START)), 200)
        np.testing.assert_allclose(state.x, reference, rtol=1e-7)

        def evaluate(x):
            e = jnp.exp(-x[1] * T)
            return x[0] * e + x[2] - Y, jnp.stack([e, -x[0] * T * e, jnp.ones_like(T)], axis=1)

        @jax.jit
        @jax.vmap
        def step(x, r, jac, cost, lam):
            state = State(x, r, jac, cost, lam)
            trial = solver.ask(state)[0]
            r_new, jac_new = evaluate(trial)
            state = solver.tell(state, trial[None], r_new[None], jac_new[None])
            return state.x, state.r, state.jac, state.cost, state.damping

        starts = jnp.array([START, [1.5, 3.0, 0.5]])
        carry = (starts, jnp.zeros((2, T.size)), jnp.zeros((2, T.size, 3)),
                 jnp.full(2, jnp.inf), jnp.full(2, 1e-2))  # fmt: skip
        for _ in range(200):
            carry = step(*carry)
        np.testing.assert_allclose(np.asarray(carry[0]), [reference, reference], rtol=1e-7)


def test_a_line_search_that_cannot_descend_within_its_tolerance_stops_without_halving(reference):
    """At the minimum, a Gauss-Newton step under ``tolerance`` of every naive standard error
    that does not lower the cost (the exact simulator's noise floor) is a minimum: one trial,
    not a halving down to ``shortest`` (each trial an exact run of every recording)."""
    x = reference.copy()
    r = _residual(x)
    # A cost a hair above the minimum's, so the Gauss-Newton step (about 0) cannot lower it.
    tried = []

    def evaluate(xs):
        tried.append(xs)
        return _evaluate(xs)[0] + 1e-9, None

    for tolerance, trials in ((0.1, 1), (None, 7)):  # 1, 1/2, ..., 1/64
        tried.clear()
        solver = line_search(tolerance=tolerance, shortest=1 / 64)
        state = minimize(solver, evaluate, solver.init(x, r, _jacobian(x)), 10)
        assert state.done and state.converged and len(tried) == trials
        np.testing.assert_array_equal(state.x, x)


def test_a_weighted_objective_reaches_the_criterions_own_minimum():
    """``objective`` (a joint fit's: each recording against its own floor): the host solver's
    reweighted steps reach the minimum of sum_k n log(mse_k + f_k^2) that scipy's minimize
    finds on that criterion itself, where plain least squares lands elsewhere. Two
    "recordings" of the curve: one clean (floor 1e-3), one that the model cannot follow (a
    slow wave of 0.1 added, twice as many samples)."""
    from scipy.optimize import minimize as scipy_minimize

    t2 = np.linspace(0.0, 2.0, 120)
    y2 = TRUTH[0] * np.exp(-TRUTH[1] * t2) + TRUTH[2] + 0.1 * np.sin(3.0 * t2)
    floors = np.array([1e-3, 1e-3])

    def residual(x):
        return np.concatenate([_residual(x), x[0] * np.exp(-x[1] * t2) + x[2] - y2])

    def jacobian(x):
        e = np.exp(-x[1] * t2)
        return np.vstack([_jacobian(x), np.column_stack([e, -x[0] * t2 * e, np.ones_like(t2)])])

    def parts(r):
        return r[: T.size], r[T.size :]

    def criterion(r):
        mse = np.array([np.mean(p**2) for p in parts(r)])
        return float(np.sum(50.0 * np.log(mse + floors**2)))

    def objective(r):
        mse = np.array([np.mean(p**2) for p in parts(r)])
        w = 50.0 / (np.array([T.size, t2.size]) * (mse + floors**2))
        return criterion(r), np.repeat(w / w.max(), [T.size, t2.size])

    def evaluate(xs):
        return np.stack([residual(x) for x in xs]), np.stack([jacobian(x) for x in xs])

    solver = levenberg_marquardt(dampings=LM_DAMPING, give_up=True, damping_range=(1e-12, 1e10),
                                 objective=objective)  # fmt: skip
    state = minimize(solver, evaluate, solver.init(START, residual(START), jacobian(START)), 300)
    best = scipy_minimize(lambda x: criterion(residual(x)), state.x, method="Nelder-Mead",
                          options={"xatol": 1e-12, "fatol": 1e-14, "maxiter": 20000}).x  # fmt: skip
    np.testing.assert_allclose(state.x, best, rtol=1e-6)
    assert criterion(residual(state.x)) <= criterion(residual(best)) + 1e-9
    plain = least_squares(residual, START, jac=jacobian, xtol=1e-14, ftol=1e-14).x
    assert np.max(np.abs(plain - state.x)) > 1e-2  # the weighting is what moves it
    # The clean recording is fitted near its own noise; plain least squares gives it up.
    assert np.sqrt(np.mean(_residual(state.x) ** 2)) < 0.5 * np.sqrt(np.mean(_residual(plain) ** 2))
