"""The damped least-squares step every fit of the engine takes (NumPy or JAX arrays), and the
host-side drivers that take it for one problem at a time (``jaxcart fit``): Levenberg-Marquardt
with several dampings tried per iteration, and the Adam start of a long fit (optax's). The
batched driver of many candidate structures at once is :mod:`tuning.estimation.engine.batch`.

Levenberg-Marquardt with Marquardt's diagonal scaling: the step solves
(J^T J + lam D) delta = -J^T r, D the diagonal of J^T J (a column the data do not see gets a
tiny floor so the system stays solvable). lam -> 0 is the Gauss-Newton step; a large lam a
short step along the scaled gradient.
"""

from __future__ import annotations

import functools
import math

import jax
import numpy as np
import optax

from jaxcart.errors import UserError
from tuning.estimation.engine.noise import effective_samples

#: Largest Levenberg-Marquardt step per iteration, in internal units.
MAX_STEP = 1.0
#: Damping values tried at once in each Levenberg-Marquardt iteration, as multiples of the
#: current one (the classic sequence lambda, 4 lambda, ... in one batch; the least damped that
#: decreases the cost is taken, then lambda / 5): a batch of K trial steps costs about one run
#: on a CPU (loop overhead bound), so a rejected step no longer costs a run of its own.
LM_DAMPING = (1.0, 4.0, 16.0, 64.0)
#: Levenberg-Marquardt converges when the step moves the parameters by less than this fraction
#: of a standard error (one that the residual supports, :func:`effective_samples`): at the
#: narrowest width, and at the wider ones of a continuation (whose result is only a start).
LM_TOLERANCE = 0.01
LM_TOLERANCE_WIDE = 0.1


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


def levenberg_marquardt(problem, theta, active, width, iterations, tolerance=LM_TOLERANCE):
    """Levenberg-Marquardt (Marquardt's diagonal scaling) on the active entries of theta (a
    float vector, internal units; ``active`` a boolean mask) of ``problem``, which gives
    ``evaluate(theta, width)`` -> (residuals, Jacobian), ``evaluate_batch(thetas, width)`` ->
    the same stacked, ``clip_bounded(theta)``, ``split(r)`` (the residual per recording) and
    ``n_params`` (entries from it on are nuisances: no trust-region flag); each
    iteration tries the damping values :data:`LM_DAMPING` in one batched evaluation and keeps
    the least damped that decreases the cost. Converged when a step moves the parameters by
    under ``tolerance`` of a standard error that the residual supports (or no step decreases
    the cost).
    Returns (theta, r, J, iterations done, converged)."""
    r, jac = problem.evaluate(theta, width)
    cost = float(r @ r)
    if not math.isfinite(cost):
        raise UserError(
            "the model does not simulate at the starting values (not finite); "
            "give starting values closer to the cart's (a plant file, --plant FILE, or the "
            "recording's [plant] table); where a warning above says a column is in other "
            "units, fix that first"
        )
    lam = 1e-3
    done = 0
    idx = np.flatnonzero(active)
    if idx.size == 0:
        return theta, r, jac, 0, True
    n_eff = effective_samples(problem.split(r))
    while done < iterations:
        done += 1
        ja = jac[:, idx]
        # A loop that runs away (unstable gains, a clock in ms) may overflow the normal
        # equations: its trial steps are then not finite, and none decreases the cost.
        with np.errstate(over="ignore", invalid="ignore"):
            g = ja.T @ r
            b = ja.T @ ja
        best = None
        while best is None and lam < 1e10:
            lams = lam * np.asarray(LM_DAMPING)
            trials, clipped = [], []
            for lam_k in lams:
                try:
                    step = marquardt_step(b, g, lam_k)
                except np.linalg.LinAlgError:
                    step = np.zeros(idx.size)
                # Trust region: each entry moves at most MAX_STEP internal units (an e-fold
                # of a parameter, 1 mm of y0) per iteration; far from the optimum the
                # Gauss-Newton step can throw a log-parameter to where the data no longer
                # depend on it.
                clipped.append(bool(np.any(np.abs(step[idx < problem.n_params]) > MAX_STEP)))
                trial = theta.copy()
                trial[idx] += np.clip(step, -MAX_STEP, MAX_STEP)
                trials.append(problem.clip_bounded(trial))
            r_k, jac_k = problem.evaluate_batch(trials, width)
            costs = np.einsum("kn,kn->k", r_k, r_k)
            costs[~np.isfinite(costs)] = np.inf
            ok = np.flatnonzero(costs <= cost)
            if ok.size:
                best = int(ok[0])
                lam = max(lams[best] / 5, 1e-12)
            else:
                lam = lams[-1] * 4
        if best is None:
            return theta, r, jac, done, True  # no step decreases the cost: a minimum
        decrease = cost - float(costs[best])
        theta, r, jac, cost = trials[best], r_k[best], jac_k[best], float(costs[best])
        # The residual whitens as the fit improves: n_eff of the current one, not the start's.
        n_eff = effective_samples(problem.split(r))
        # Near the minimum d cost = sum (d theta / stderr)^2 sigma^2 N / n_eff (the stderr that
        # n_eff independent samples support): under tolerance^2 the step moved by less than
        # ``tolerance`` of a standard error.
        if not clipped[best] and decrease <= tolerance**2 * cost / n_eff:
            return theta, r, jac, done, True
    return theta, r, jac, done, False


def adam(problem, theta, active, width, steps, lr):
    """Adam with a cosine-decayed step (``optax.adam(optax.cosine_decay_schedule(lr, steps))``)
    on the active entries of theta; ``problem`` as for :func:`levenberg_marquardt`. Returns
    (the best point met, its cost)."""
    if steps <= 0 or not np.any(active):
        return theta, None
    init, update = _adam(float(lr), int(steps))
    state = init(theta[active])
    best, best_cost = theta.copy(), np.inf
    current = theta.copy()
    for _ in range(steps):
        r, jac = problem.evaluate(current, width)
        cost = float(r @ r)
        if not math.isfinite(cost):
            break
        if cost < best_cost:
            best, best_cost = current.copy(), cost
        grad = jac[:, active].T @ r / max(cost, 1e-300)  # scale-free (adam normalizes anyway)
        step, state = update(grad, state)
        current = current.copy()
        current[active] += np.asarray(step)
    return best, best_cost


@functools.cache
def _adam(lr: float, steps: int):
    """(init, update) of optax's adam on its cosine decay, each one compiled program: run
    eagerly, their dozen small operations compile a program each in every new process
    (measured, 2 cores at load 10: the first update 1.9 s eager, 0.54 s jitted)."""
    optimizer = optax.adam(optax.cosine_decay_schedule(lr, steps))
    return jax.jit(optimizer.init), jax.jit(optimizer.update)
