"""Quantities accumulated while the smooth loop runs, instead of from stored traces.

A loss built from a stored response keeps every sample (3001 per run) and, under reverse-mode
differentiation, the whole carry of every step as well: tens of MB per batch, out of cache.
:func:`accumulate` folds each sample into a small accumulator inside the ``lax.scan`` of
:func:`jaxcart.smooth_sim.loop`, so nothing per-sample is stored; with forward-mode derivatives
(:func:`value_and_jacfwd_rows`) the tangents ride along in the same carry.

>>> import jax.numpy as jnp
>>> from jaxcart import PID, handout_plant, step
>>> def peak(acc, k, t, s):
...     return jnp.maximum(acc, s.position)
>>> y_max = accumulate(handout_plant(), PID(kp=100.0, kd=2.0, v_limit=6.0), step(0.5),
...                    jnp.asarray(-jnp.inf), peak)
>>> 0.5 < float(y_max) < 0.6
True
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxcart.smooth_sim import loop

#: Samples per scan iteration: 1. Two run ~1.3x faster but double the compile time (measured:
#: seconds, where the tuner waits on compilation more than on the loop).
UNROLL = 1


def accumulate(
    plant,
    controller,
    experiment,
    init,
    update: Callable,
    *,
    smoothing=None,
    substeps=None,
    unroll: int = UNROLL,
):
    """Run the smooth loop and fold every sample into ``init``; returns the final accumulator.

    ``update(acc, k, t_k, sample) -> acc`` for sample index k (int32), time t_k - t_0 [s] and
    the :class:`jaxcart.smooth_sim.Sample` of that period (position [m] as the controller reads
    it, velocity [m/s], reference [m], command [V], voltage [V], unlimited [V]).
    """
    start, step = loop(plant, controller, experiment, smoothing=smoothing, substeps=substeps)
    t = experiment.time - experiment.time[0]

    def body(carry, xs):
        inner, acc = carry
        k, tk, signal_k = xs
        inner, sample = step(inner, signal_k)
        return (inner, update(acc, k, tk, sample)), None

    ks = jnp.arange(experiment.n_samples, dtype=jnp.int32)
    carry, _ = jax.lax.scan(body, (start, init), (ks, t, experiment.signal), unroll=unroll)
    return carry[1]


def value_and_jacfwd_rows(fn: Callable, *, has_aux: bool = False) -> Callable:
    """``f(U, rows, *shared) -> (values, grads)`` (``((values, aux), grads)`` with ``has_aux``)
    of a scalar ``fn(u, row, *shared)`` for each row u of U (B, n) and the matching item of
    ``rows`` (a pytree with leading axis B, or None), by forward mode: one tangent per entry
    of u, so the primal runs once and the n tangents ride along (cheaper than reverse mode for
    a few parameters, and nothing is stored for a backward pass). grads has U's shape.

    The tangents are laid out (n, B), the runs on the minor axis, so each tangent's update
    vectorizes across the runs like the primal's; per-run Jacobians (``jacfwd`` under
    ``vmap``) give (B, n), which vectorizes across the n tangents only: 4x slower where loops
    compile whole (jaxcart.xlaflags; the bench's gradient row at 128 runs per chunk, measured).
    """

    def run(U, rows, *shared):
        def f(V):
            out = jax.vmap(lambda u, row: fn(u, row, *shared))(V, rows)
            return out if has_aux else (out, None)

        n = U.shape[-1]
        basis = jnp.broadcast_to(jnp.eye(n, dtype=U.dtype)[:, None, :], (n, *U.shape))

        def along(t):
            value, dvalue, aux = jax.jvp(f, (U,), (t,), has_aux=True)
            return value, aux, dvalue

        value, aux, tangents = jax.vmap(along, out_axes=(None, None, 0))(basis)
        return ((value, aux) if has_aux else value), jnp.moveaxis(tangents, 0, -1)

    return run
