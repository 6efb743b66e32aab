"""Gauss-Newton on the exact simulator's residuals: the last step of every fit of the engine.

The smooth model differs from the exact one by a little: a breakaway from rest lags by about
one sub-step, the corners are rounded, a cart at rest creeps at F w / f_c. Against encoder
noise of a few micrometres that little is a bias of several standard errors, in the fitted
values and in the Jacobian the standard errors come from. The exact model is piecewise smooth
in the parameters (stop times are found in closed form), so its difference quotients are
clean: forward differences, one exact run per parameter. Central differences cost two: on a
closed-loop P 50 step (B_eq and f_c fitted, encoder-quantized) they took 42 exact runs instead
of 24 and moved the fitted values by under 3e-5 standard errors and the standard errors by 7e-5
(relative); on a tap the two Jacobians agree to 5e-7 (``tests/test_exact_polish.py``).
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import numpy as np

from tuning.estimation.engine import parameters
from tuning.estimation.engine.least_squares import gauss_newton_step, line_search, minimize

#: Secant half-width in a fit's internal units (3 % of a log-fitted parameter) where the exact
#: output's staircase flattens a forward difference (:func:`jacobian`).
STAIRCASE = 0.03
#: A step under this share of every naive standard error ends the polish (converged).
TOLERANCE = 0.1


class Polished(NamedTuple):
    """``x``: the values; ``r``: the residual there; ``jac``: the forward-difference Jacobian
    at ``x`` (None after 0 iterations); ``improved``: the cost fell; ``iterations`` done;
    ``converged``: stopped by no descent or a step under ``tolerance`` of a standard error,
    not by the iteration count."""

    x: np.ndarray
    r: np.ndarray
    jac: np.ndarray | None
    improved: bool
    iterations: int
    converged: bool


def jacobian(residuals, x, r, steps, reference=None, staircase=None) -> np.ndarray:
    """Forward differences of ``residuals`` (points -> their residuals, :func:`gauss_newton`)
    at ``x`` (residual ``r`` there) with ``steps``: every column's point in one call, so that
    their runs are made at once, several at a time.

    Where an event snaps to a sample (a breakaway at f_s, say) the exact output moves in steps,
    and a small difference quotient is 0 although the data depend on the parameter: a column
    under 1e-3 of its ``reference`` norm (the smooth model's; 0 for a parameter that does not
    act) is replaced by a central secant over +-``staircase`` (a number or one per entry),
    which spans the steps."""
    ups = [_moved(x, i, h) for i, h in enumerate(steps)]
    jac = np.stack([(r_up - r) / h for r_up, h in zip(residuals(ups), steps, strict=True)], axis=1)
    if reference is None or staircase is None:
        return jac
    half = np.broadcast_to(np.asarray(staircase, dtype=float), x.shape)
    flat = np.flatnonzero(np.linalg.norm(jac, axis=0) < 1e-3 * np.asarray(reference))
    if flat.size == 0:
        return jac
    runs = residuals([_moved(x, j, sign * half[j]) for j in flat for sign in (1, -1)])
    for k, j in enumerate(flat):
        jac[:, j] = (runs[2 * k] - runs[2 * k + 1]) / (2 * half[j])
    return jac


def _moved(x, i, h):
    """``x`` with entry ``i`` moved by ``h``."""
    out = x.copy()
    out[i] += h
    return out


def gauss_newton(
    residuals,
    x0,
    steps,
    bounds,
    iterations: int,
    *,
    max_step: float | None = None,
    shortest: float = 1 / 64,
    tolerance: float = TOLERANCE,
    reference=None,
    staircase: float | None = None,
    target: float | None = None,
) -> Polished:
    """Gauss-Newton on ``residuals`` (the engine's
    :func:`~tuning.estimation.engine.least_squares.line_search`, driven by its ``minimize``):
    a list of parameter vectors -> the list of their residuals (one array [m] each); the points
    of a Jacobian come in one call, so that their runs are made at once; a line search's trials
    one at a time (most are taken at once).

    x0: the start (p,), inside the bounds; steps: the forward-difference steps (p,), or a
    function of x giving them; bounds: (low, high) arrays (p,) every trial is clipped to;
    iterations: at most this many steps. Each iteration takes the Gauss-Newton step (each entry
    clipped to +-``max_step``), halved until the cost falls (down to ``shortest`` of it: no
    descent is a minimum); a step under ``tolerance`` of every naive standard error
    converges. ``reference``, ``staircase``: see :func:`jacobian`. ``target``: a
    cost worth fitting for; where even the Gauss-Newton model's least cost at the start,
    |r + J step|^2, is above it, the fit stops after the first Jacobian (nothing improved:
    what cannot come near a better model is not fitted to the end). The Jacobian returned is
    the one at the values returned (the standard errors are computed from it)."""
    x = np.asarray(x0, dtype=float).copy()
    r = residuals([x])[0]
    if x.size == 0 or iterations <= 0 or not math.isfinite(float(r @ r)):
        return Polished(x, r, None, False, 0, True)
    step_of = steps if callable(steps) else (lambda _x: np.asarray(steps, dtype=float))

    def jacobian_at(x, r):
        return jacobian(residuals, x, r, step_of(x), reference, staircase)

    solver = line_search(bounds=bounds, max_step=max_step, shortest=shortest, tolerance=tolerance)
    start = solver.init(x, r, jacobian_at(x, r))
    if target is not None:
        reach = r + start.jac @ gauss_newton_step(start.jac, r)
        if float(reach @ reach) > target:
            return Polished(x, r, start.jac, False, 0, False)
    end = minimize(solver, lambda xs: (residuals(list(xs)), None), start, iterations, jacobian_at)
    return Polished(end.x, end.r, end.jac, end.cost < start.cost, end.iterations, end.converged)


def difference_floors(names) -> np.ndarray:
    """The least forward-difference step of each value of ``names``: a time or a position
    [s, m] 1e-7, any other (a force, a gain) 1e-6."""
    return np.array(
        [
            1e-7
            if parameters.base_name(n) in parameters.NUISANCE
            or parameters.spec(n).unit in ("s", "m")
            else 1e-6
            for n in names
        ]
    )


def difference_steps(names, x) -> np.ndarray:
    """Forward-difference steps of the values ``x`` of ``names``: 1e-4 of each, at least its
    floor (:func:`difference_floors`)."""
    return 1e-4 * np.abs(np.asarray(x, dtype=float)) + difference_floors(names)


def _staircase(names, x, reference, slopes) -> dict:
    """Where the exact output moves in steps of a value (a breakaway at f_s snapped to a
    sample, a controller reading whole counts), a forward difference is flat: the secant spans
    STAIRCASE of its internal coordinate (``slopes``: d value / d coordinate of each; default
    :func:`~.parameters.value_slope`), where the smooth fit's Jacobian sees the value act
    (``reference``: its column norms per unit of each value; :func:`jacobian`)."""
    if slopes is None:
        slopes = [parameters.value_slope(n, v) for n, v in zip(names, x, strict=True)]
    return {"reference": reference, "staircase": STAIRCASE * np.abs(np.asarray(slopes))}


def polish(
    residuals, names, x, iterations, *, reference, bounds=None, slopes=None, steps=None,
    max_step=None, shortest=0.25, target=None, rows=None,
) -> Polished:  # fmt: skip
    """The exact polish of every fit of the engine (``jaxcart fit``'s last step, a diagnosis's
    polish and held-out re-fits): :func:`gauss_newton` on ``residuals`` (vectors of ``names``'
    coordinates -> their residuals) from ``x``, within ``bounds`` ((low, high); default
    :func:`~.parameters.bounds`), the staircase's secants of :func:`_staircase` (``reference``,
    ``slopes``, column norms of the residual scaled by ``rows``); ``target``: a cost [m^2] worth
    fitting for (see :func:`gauss_newton`). ``rows``: each residual's factor, the square root of
    its recording's weight in a joint fit
    (:meth:`~tuning.estimation.engine.noise.RecordingNoise.weights`): the least squares of the
    scaled residuals, whose residual and Jacobian are returned unscaled (None: 1).

    The coordinates are the values themselves unless the caller says otherwise: forward
    differences of :func:`difference_steps` (``steps``: others, a number or one per entry),
    no limit on a step (``max_step``), a step halved down to ``shortest`` of it. ``jaxcart
    fit`` polishes in its internal coordinates (a logarithm for a positive parameter): steps
    of 1e-6, at most MAX_STEP, slopes 1 (on its runs the value coordinates' steps of 1e-4
    merge M and B_eq into one correlated pair where they are one combination, and leave a
    track-friction element 4 standard errors off)."""
    if bounds is None:
        bounds = tuple(
            np.array([parameters.bounds(n)[k] for n in names], dtype=float) for k in (0, 1)
        )
    x = np.asarray(x, dtype=float)
    if steps is None:
        steps = partial(difference_steps, names)
    if rows is not None:
        plain = residuals

        def residuals(xs):
            return [r * rows for r in plain(xs)]

    done = gauss_newton(
        residuals,
        np.clip(x, *bounds),
        steps if callable(steps) else np.broadcast_to(np.asarray(steps, dtype=float), x.shape),
        bounds,
        iterations,
        max_step=max_step,
        shortest=shortest,
        target=target,
        **_staircase(names, x, reference, slopes),
    )
    if rows is None:
        return done
    jac = None if done.jac is None else done.jac / rows[:, None]
    return done._replace(r=done.r / rows, jac=jac)


def values_jacobian(residuals, names, x, *, reference, slopes=None) -> np.ndarray:
    """The forward-difference Jacobian of ``residuals`` (vectors of ``names``' values -> their
    residuals) at their values ``x``, as :func:`polish` takes it [m per unit of each value]."""
    x = np.asarray(x, dtype=float)
    steps = difference_steps(names, x)
    return jacobian(
        residuals, x, residuals([x])[0], steps, **_staircase(names, x, reference, slopes)
    )
