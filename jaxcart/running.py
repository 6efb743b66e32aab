"""Quantities accumulated while the smooth loop runs, instead of from stored traces.

A loss built from a stored response keeps every sample (3001 per run) and, under reverse-mode
differentiation, the whole carry of every step as well: tens of MB per batch, out of cache.
:func:`accumulate` folds each sample into a small accumulator inside the ``lax.scan`` of
:func:`jaxcart.smooth.loop`, so nothing per-sample is stored; with forward-mode derivatives
(:func:`value_and_jacfwd`) the tangents ride along in the same carry.

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

from jaxcart.smooth import loop

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
    the :class:`jaxcart.smooth.Sample` of that period (position [m] as the controller reads
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
    (_, acc), _ = jax.lax.scan(body, (start, init), (ks, t, experiment.signal), unroll=unroll)
    return acc


def value_and_jacfwd(fn: Callable, *, has_aux: bool = False) -> Callable:
    """``f(u, *args) -> (value, grad)`` (or ``((value, aux), grad)`` with ``has_aux``) of a
    scalar ``fn`` of a vector u (first argument), by forward mode: one tangent per entry,
    vmapped, so the primal runs once and the n tangents ride along (cheaper than reverse mode
    for a few parameters, and nothing is stored for a backward pass)."""

    def run(u, *args):
        def f(x):
            if has_aux:
                value, aux = fn(x, *args)
                return value, (value, aux)
            value = fn(x, *args)
            return value, value

        grad, out = jax.jacfwd(f, has_aux=True)(u)
        return out, grad

    return run
