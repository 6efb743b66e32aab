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
    pack: bool = False,
):
    """Run the smooth loop and fold every sample into ``init``; returns the final accumulator.

    ``update(acc, k, t_k, sample) -> acc`` for sample index k (int32), time t_k - t_0 [s] and
    the :class:`jaxcart.smooth.Sample` of that period (position [m] as the controller reads
    it, velocity [m/s], reference [m], command [V], voltage [V], unlimited [V]).
    ``pack``: carry the loop's state and each tuple of accumulators as one vector (see below)
    for a small batch, such as the tuner's starts; a wide batch (thousands of runs) is several
    times slower packed (the bench's gradient row: 3.9x, measured).
    """
    start, step = loop(plant, controller, experiment, smoothing=smoothing, substeps=substeps)
    t = experiment.time - experiment.time[0]
    # Linear between samples, the loop's state rides in one vector, and so does each tuple of
    # accumulators at the top of ``init`` (see _packer): 1.3x faster for the tuner's loss on a
    # CPU (tuning.losses.stream_loss). Not with force effects: XLA then inlines the sub-steps
    # into that vector's pass once per entry, 5x slower (both measured: forward mode).
    if not pack or plant.stage("force"):
        pack, unpack = _same, _same
    else:
        pack, unpack = _carry_packer(start, init)

    def body(carry, xs):
        inner, acc = unpack(carry)
        k, tk, signal_k = xs
        inner, sample = step(inner, signal_k)
        return pack((inner, update(acc, k, tk, sample))), None

    ks = jnp.arange(experiment.n_samples, dtype=jnp.int32)
    carry, _ = jax.lax.scan(body, pack((start, init)), (ks, t, experiment.signal), unroll=unroll)
    return unpack(carry)[1]


def _carry_packer(start, init):
    """(pack, unpack) of the carry (state, accumulator): _packer for the state and for each
    tuple at the top of a tuple ``init``; anything else as it is."""
    groups = [i for i, x in enumerate(init) if type(x) is tuple] if type(init) is tuple else []
    state = _packer(start)
    accs = {i: _packer(init[i]) for i in groups}

    def pack(carry):
        inner, acc = carry
        if groups:
            acc = tuple(accs[i][0](x) if i in accs else x for i, x in enumerate(acc))
        return state[0](inner), acc

    def unpack(carry):
        inner, acc = carry
        if groups:
            acc = tuple(accs[i][1](x) if i in accs else x for i, x in enumerate(acc))
        return state[1](inner), acc

    return pack, unpack


def _same(tree):
    return tree


def _packer(tree):
    """(pack, unpack) between ``tree`` and (one vector of its scalar leaves of the commonest
    float dtype, the other leaves). XLA on a CPU computes every array a loop carries in its own
    pass over the loop body (its tangents in another), each recomputing what that array
    depends on: one vector is one pass instead of one per state variable. Only the order of
    operations changes (fused multiply-adds can round otherwise, by an ulp)."""
    leaves, treedef = jax.tree.flatten(tree)
    dtypes = [jnp.result_type(x) for x in leaves]
    scalar = [jnp.ndim(x) == 0 for x in leaves]
    floats = [
        d for d, s in zip(dtypes, scalar, strict=True) if s and jnp.issubdtype(d, jnp.floating)
    ]
    dtype = max(set(floats), key=floats.count) if floats else None
    mine = [s and d == dtype for d, s in zip(dtypes, scalar, strict=True)]

    def pack(tree):
        leaves = jax.tree.leaves(tree)
        vec = [x for x, m in zip(leaves, mine, strict=True) if m]
        rest = [x for x, m in zip(leaves, mine, strict=True) if not m]
        return (jnp.stack(vec) if vec else None), rest

    def unpack(packed):
        vec, rest = packed
        rest = iter(rest)
        out, i = [], 0
        for m in mine:
            if m:
                out.append(vec[i])
                i += 1
            else:
                out.append(next(rest))
        return jax.tree.unflatten(treedef, out)

    return pack, unpack


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
