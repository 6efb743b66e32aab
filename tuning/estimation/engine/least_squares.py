"""The engine's least-squares solvers, one contract for all of them, as optax's
``GradientTransformation`` is one for first-order optimizers. A solver is a :class:`Solver`:

    state = solver.init(x, r, jac)                  the start: its residual and Jacobian
    trials = solver.ask(state)                      (k, p): the points to evaluate next
    state = solver.tell(state, trials, rs, jacs)    their residuals (k, m) and Jacobians

and :func:`minimize` drives any of them on the host (``jaxcart fit``'s smooth fit, the exact
polish of every fit, a held-out re-fit's step), while a diagnosis's batch runs one ask, its
forward pass and one tell of :func:`compiled_marquardt` inside each compiled, vmapped step
(:mod:`tuning.estimation.engine.batch`). (An earlier form that ran the host solver's
several-damping machinery there compiled and ran twice as long; this one is the batch's own
arithmetic, and its diagnoses are the same to every digit and as fast: a joint diagnosis of the
built-in tap and P 50 run without the compilation cache, 18.1 and 18.3 s against 18.3 and
17.7 s, measured 2026-12-06.)

- :func:`levenberg_marquardt`: Marquardt's diagonal scaling, the step solves
  (J^T J + lam D) delta = -J^T r, D the diagonal of J^T J (a column the data do not see gets a
  tiny floor so the system stays solvable); several dampings may be tried per ask (a batch of
  K trial steps costs about one run on a CPU).
- :func:`compiled_marquardt`: the same step in JAX, one damping an ask, for a compiled step
  (bounds and held entries may be traced values; a weighted objective takes reweighted steps).
- :func:`line_search`: Gauss-Newton (or any ``direction``) halved until the cost falls; a
  point it takes needs its Jacobian anew (``state.jac`` None: :func:`minimize`'s ``jacobian``).

Also here: the Adam start of a long fit (optax's adam on its cosine decay, :func:`adam`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

#: Largest Levenberg-Marquardt step per iteration, in internal units.
MAX_STEP = 1.0
#: Damping values tried at once in each Levenberg-Marquardt iteration of a host fit, as
#: multiples of the current one (the classic sequence lambda, 4 lambda, ... in one batch; the
#: least damped that decreases the cost is taken, then lambda / 5): a batch of K trial steps
#: costs about one run on a CPU (loop overhead bound), so a rejected step no longer costs a run
#: of its own.
LM_DAMPING = (1.0, 4.0, 16.0, 64.0)
#: Levenberg-Marquardt converges when the step moves the parameters by less than this fraction
#: of a standard error (one that the residual supports): at the narrowest width, and at the
#: wider ones of a continuation (whose result is only a start).
LM_TOLERANCE = 0.01
LM_TOLERANCE_WIDE = 0.1


class State(NamedTuple):
    """Where a solver stands: the accepted point ``x`` (p,), its residual ``r`` (m,) and
    Jacobian ``jac`` (m, p) (None: to be made at ``x``), their ``cost``, the ``damping`` (the
    Levenberg-Marquardt lambda, or a line search's fraction of its step), the ``iterations``
    done, whether it is ``done`` and whether that was ``converged`` (not an iteration cap)."""

    x: Any
    r: Any
    jac: Any
    cost: Any
    damping: Any
    iterations: Any = 0
    done: Any = False
    converged: Any = False


class Solver(NamedTuple):
    """``init(x, r, jac)`` -> State; ``ask(state)`` -> trial points (k, p); ``tell(state,
    trials, rs, jacs)`` -> State (``jacs`` None where the evaluation makes none)."""

    init: Callable
    ask: Callable
    tell: Callable


def marquardt_step(jtj, g, lam, free=None, xp=np):
    """The step delta for damping ``lam`` from J^T J (``jtj``) and J^T r (``g``); ``free``: 1 for
    the entries that move, 0 for those held (their delta is 0)."""
    d = xp.diag(jtj)
    if free is None:
        free = xp.ones_like(d)
    reg = xp.where(free > 0, lam * (d + 1e-9 * xp.max(d)) + 1e-30, 1.0)
    return -xp.linalg.solve(jtj + xp.diag(reg), g) * free


def gauss_newton_step(jac, r):
    """The undamped step: the least-squares solution of J delta = -r, columns scaled to unit
    norm first (the parameters' units differ by orders of magnitude)."""
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    step, *_ = np.linalg.lstsq(jac / scale, -np.asarray(r), rcond=None)
    return step / scale


def standard_errors(jac, r) -> np.ndarray:
    """The naive standard errors sigma sqrt(diag (J^T J)^+) of the Gauss-Newton model."""
    b_pinv = np.linalg.pinv(jac.T @ jac)
    dof = max(r.size - jac.shape[1], 1)
    return np.sqrt(np.maximum(np.diag(b_pinv) * float(r @ r) / dof, 1e-300))


def levenberg_marquardt(
    *,
    dampings=(1.0,),
    shrink: float = 3.0,
    grow: float = 4.0,
    damping_range=(1e-7, 1e7),
    give_up: bool = False,
    bounds=(-np.inf, np.inf),
    max_step: float | None = None,
    trusted=None,
    tolerance: Callable | None = None,
    free=None,
    objective: Callable | None = None,
) -> Solver:
    """Levenberg-Marquardt with Marquardt's diagonal scaling (NumPy, on the host).

    Each ask tries the damping times each of ``dampings``; tell keeps the least damped trial
    whose cost is finite and lower, then divides its damping by ``shrink``, else multiplies
    the largest by ``grow``, within ``damping_range`` (``give_up``: reaching its top is a
    minimum, done). Trials are clipped to ``bounds`` (low, high), each entry's step to
    +-``max_step`` (a trust region; an entry of ``trusted`` whose step was cut rules out
    convergence on that iteration); ``free``: 1 for the entries that move. ``tolerance(r)`` ->
    d: converged once a step to the residual ``r`` lowers the cost by under d (None: never;
    the caller counts iterations). ``objective(r)`` -> (cost, row weights), as
    :func:`compiled_marquardt` takes it: iteratively reweighted steps, the weights at the
    accepted point (default: r @ r, weights 1)."""
    dampings = tuple(float(d) for d in dampings)
    low, high = damping_range
    if objective is None:

        def objective(r):
            return float(r @ r), None

    def init(x, r, jac, damping=1e-3):
        return State(x, r, jac, objective(r)[0], damping)

    def raw_steps(state):
        jw = state.jac if free is None else state.jac * free[None, :]  # a held entry's column
        r = state.r
        weights = objective(r)[1]
        if weights is not None:
            root = np.sqrt(weights)
            jw, r = jw * root[:, None], r * root
        # A loop that runs away may overflow the normal equations: its trial steps are then
        # not finite, and none decreases the cost.
        with np.errstate(over="ignore", invalid="ignore"):
            jtj, g = jw.T @ jw, jw.T @ r
        return [_solved(jtj, g, state.damping * d, free) for d in dampings]

    def ask(state):
        steps = raw_steps(state)
        if max_step is not None:
            steps = [np.clip(s, -max_step, max_step) for s in steps]
        return np.stack([np.clip(state.x + s, *bounds) for s in steps])

    def tell(state, trials, rs, jacs):
        costs = np.array([objective(r)[0] for r in rs])
        ok = np.isfinite(costs) & (costs < state.cost)
        if not ok.any():
            lam = min(state.damping * dampings[-1] * grow, high)
            stop = give_up and lam >= high
            return state._replace(damping=lam, iterations=state.iterations + stop, done=stop,
                                  converged=stop)  # fmt: skip
        best = int(np.argmax(ok))  # the least damped that decreases the cost
        cost = float(costs[best])
        converged = False
        if tolerance is not None:
            cut = _cut(raw_steps(state)[best], max_step, trusted)
            converged = not cut and state.cost - cost <= tolerance(rs[best])
        # Copies in C order: a row of the evaluation's (k, m, p) block may be strided, and
        # the normal equations' rounding follows the layout (1e-14 in a step).
        return State(
            np.ascontiguousarray(trials[best]),
            np.ascontiguousarray(rs[best]),
            np.ascontiguousarray(jacs[best]),
            cost,
            max(state.damping * dampings[best] / shrink, low),
            state.iterations + 1,
            converged,
            converged,
        )

    return Solver(init, ask, tell)


def compiled_marquardt(*, bounds, free, objective=None) -> Solver:
    """Levenberg-Marquardt inside a compiled, vmapped step (JAX: a diagnosis's batch,
    :mod:`tuning.estimation.engine.batch`): one trial an ask at the damping, kept where its
    objective is finite and lower (the damping then a third, else four times, within 1e-7 to
    1e7); a state whose cost is inf asks for its own point (a fit's first evaluation at a
    width: its residual and Jacobian), the damping kept. Arrays throughout (no host branch):
    ``bounds`` (low, high) and ``free`` (1 for an entry that moves) may be traced values.
    ``objective(r)`` -> (cost, row weights): a weighted objective takes iteratively reweighted
    steps, the weights at the accepted point (default: r @ r, weights 1). No convergence test:
    the caller counts its iterations."""
    low, high = bounds
    if objective is None:

        def objective(r):
            return r @ r, jnp.ones_like(r)

    def init(x, r, jac, damping=1e-2):
        return State(x, r, jac, objective(r)[0], damping)

    def ask(state):
        _, w = objective(state.r)
        jw = state.jac * jnp.sqrt(w)[:, None]
        delta = marquardt_step(jw.T @ jw, jw.T @ (state.r * jnp.sqrt(w)), state.damping, free,
                               xp=jnp)  # fmt: skip
        trial = jnp.where(jnp.isfinite(state.cost), jnp.clip(state.x + delta, low, high), state.x)
        return trial[None, :]

    def tell(state, trials, rs, jacs):
        cost, _ = objective(rs[0])
        ok = jnp.isfinite(cost) & (cost < state.cost)
        lam = state.damping
        grown = jnp.where(ok, jnp.maximum(lam / 3.0, 1e-7), jnp.minimum(lam * 4.0, 1e7))
        return State(
            jnp.where(ok, trials[0], state.x),
            jnp.where(ok, rs[0], state.r),
            jnp.where(ok, jacs[0], state.jac),
            jnp.where(ok, cost, state.cost),
            jnp.where(jnp.isfinite(state.cost), grown, lam),
            state.iterations + 1,
        )

    return Solver(init, ask, tell)


def _solved(jtj, g, lam, free):
    """:func:`marquardt_step`; a singular system is no step."""
    try:
        return marquardt_step(jtj, g, lam, free)
    except np.linalg.LinAlgError:
        return np.zeros(g.shape)


def _cut(step, max_step, trusted) -> bool:
    """Whether the trust region cut an entry of ``trusted`` of ``step``."""
    if max_step is None:
        return False
    moved = np.abs(step) > max_step
    return bool(np.any(moved if trusted is None else moved & trusted))


def line_search(
    *,
    bounds=(-np.inf, np.inf),
    max_step: float | None = None,
    shortest: float = 1 / 64,
    tolerance: float | None = 1e-2,
    direction: Callable = gauss_newton_step,
) -> Solver:
    """Gauss-Newton with a halving line search (NumPy): ``direction(jac, r)`` (default the
    Gauss-Newton step; each entry cut to +-``max_step``) from ``x``, tried at fractions 1,
    1/2, ... down to ``shortest`` of it, one trial per ask, each clipped to ``bounds``; the
    first that lowers the cost is taken (and needs its Jacobian: ``jac`` None), none is a
    minimum. Converged when a step moves every entry by under ``tolerance`` of its naive
    standard error, and a minimum where a step that small does not lower the cost (shorter
    ones are not tried). ``init(x, r, jac)``."""

    def init(x, r, jac, damping=1.0):
        return State(np.asarray(x, dtype=float), r, jac, float(r @ r), damping)

    def ask(state):
        step = direction(state.jac, state.r)
        if max_step is not None:
            step = np.clip(step, -max_step, max_step)
        return np.clip(state.x + state.damping * step, *bounds)[None, :]

    def tell(state, trials, rs, jacs=None):
        cost = float(rs[0] @ rs[0])
        if math.isfinite(cost) and cost < state.cost:
            small = _within(trials[0] - state.x, state, tolerance)
            return State(trials[0], rs[0], None, cost, 1.0, state.iterations + 1, small, small)
        t = state.damping / 2
        if t >= shortest and not _within(trials[0] - state.x, state, tolerance):
            return state._replace(damping=t)
        # No descent along the direction, or none within tolerance of a standard error: a
        # minimum (shorter trials would only move it by less than the tolerance).
        return state._replace(
            damping=1.0, iterations=state.iterations + 1, done=True, converged=True
        )

    return Solver(init, ask, tell)


def _within(step, state: State, tolerance) -> bool:
    """Every entry of ``step`` under ``tolerance`` (None: never) of its naive standard error at
    ``state``."""
    if tolerance is None:
        return False
    return bool(np.all(np.abs(step) <= tolerance * standard_errors(state.jac, state.r)))


def minimize(solver: Solver, evaluate, state: State, iterations: int, jacobian=None) -> State:
    """Drive ``solver`` from ``state`` until it is done or ``iterations`` are done:
    ``evaluate(trials)`` -> (residuals (k, m), Jacobians (k, m, p) or None); ``jacobian(x, r)``
    makes the Jacobian at a point the solver took without one (a line search's)."""
    while not state.done and state.iterations < iterations:
        trials = solver.ask(state)
        rs, jacs = evaluate(trials)
        state = solver.tell(state, trials, rs, jacs)
        if state.jac is None and jacobian is not None:
            state = state._replace(jac=jacobian(state.x, state.r))
    return state


def adam(problem, theta, active, width, steps, lr):
    """Adam with a cosine-decayed step (``optax.adam(optax.cosine_decay_schedule(lr, steps))``)
    on the active entries of theta of a smooth fit's ``problem`` (``evaluate(theta, width)`` ->
    (r, J); ``objective(r)`` -> (cost, row weights or None), as :func:`levenberg_marquardt`
    takes it): the start of a long fit, where the model is smoothest. Returns (the best point
    met, its residual; None without a step)."""
    if steps <= 0 or not np.any(active):
        return theta, None
    init, update = _adam(float(lr), int(steps))
    state = init(theta[active])
    best, best_r, best_cost = theta.copy(), None, np.inf
    current = theta.copy()
    for _ in range(steps):
        r, jac = problem.evaluate(current, width)
        cost, weights = problem.objective(r)
        if not math.isfinite(cost):
            break
        if cost < best_cost:
            best, best_r, best_cost = current.copy(), r, cost
        # The objective's gradient up to a factor (adam normalizes anyway): J^T W r.
        wr = r if weights is None else weights * r
        grad = jac[:, active].T @ wr / max(abs(cost), 1e-300)
        step, state = update(grad, state)
        current = current.copy()
        current[active] += np.asarray(step)
    return best, best_r


@functools.cache
def _adam(lr: float, steps: int):
    """(init, update) of optax's adam on its cosine decay, each one compiled program: run
    eagerly, their dozen small operations compile a program each in every new process
    (measured, 2 cores at load 10: the first update 1.9 s eager, 0.54 s jitted)."""
    optimizer = optax.adam(optax.cosine_decay_schedule(lr, steps))
    return jax.jit(optimizer.init), jax.jit(optimizer.update)
