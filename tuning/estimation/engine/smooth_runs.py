"""The engine's one way to simulate recordings through the smooth simulator at a vector of
values: both a fit of fixed structure (:mod:`tuning.estimation.fitting.model`) and a diagnosis's
batch of candidates (:mod:`tuning.estimation.engine.batch`) call :func:`positions`.

A diagnosis's recordings alike in everything static (the experiment's kind and sample time, the
plant's and the controller's structure, the sub-steps, the encoder in the loop) are simulated
side by side, one loop per :class:`Shape` group (``jax.vmap``): its step compiles once per kind
of run, not once per file; a fit runs each in a loop of its own (:func:`shape_of`). Each
recording reads its values from the vector through the engine's
:class:`~tuning.estimation.engine.layout.Layout`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart import plantspec
from jaxcart.smooth_sim import simulate_smooth
from tuning.estimation.engine import parameters


class Shape(NamedTuple):
    """What the simulation is specialised on (hashable: a jit static): ``groups``, the
    recordings simulated side by side (indices); ``substeps``, each recording's RK4 sub-steps
    per sample; ``counts``, each recording's encoder count [m] where its controller reads the
    counts (the encoder in the loop), else 0; ``lengths``, the samples returned of each."""

    groups: tuple
    substeps: tuple
    counts: tuple
    lengths: tuple


def shape_of(segments, plants, substeps, side_by_side=True) -> Shape:
    """The :class:`Shape` of ``segments`` (:class:`~.segments.Segment`) on ``plants`` with
    ``substeps`` per sample, each returning its target's length. ``side_by_side``: the
    recordings alike in everything static in one loop, else each in its own. One loop compiles
    once per kind of run (a diagnosis's step: every round reuses it); on the CPU two lanes of
    one loop run slower than two loops (a fit of the real P 50 step, its repeat and the PD run:
    16.1 s side by side, 11.3 s apart)."""
    counts = tuple(float(s.quantization) if s.counts_in_loop else 0.0 for s in segments)
    groups: dict = {}
    for i, (seg, plant) in enumerate(zip(segments, plants, strict=True)):
        exp = seg.experiment
        key = (
            i if not side_by_side else -1,
            exp.kind,
            float(exp.sample_time),
            jax.tree_util.tree_structure(plant),
            jax.tree_util.tree_structure(seg.controller),
            substeps[i],
            counts[i],
        )
        groups.setdefault(key, []).append(i)
    return Shape(
        tuple(tuple(g) for g in groups.values()),
        tuple(int(n) for n in substeps),
        counts,
        tuple(s.target.size for s in segments),
    )


def padded(segments, shape: Shape, multiple: int = 1) -> list:
    """Each recording's experiment with its signal held at its last value to the longest of
    its group, rounded up to a ``multiple`` of samples (the samples past its end are simulated
    and dropped or weighed 0; recordings of nearly one length then share a compilation)."""
    out = [None] * len(segments)
    for group in shape.groups:
        n = max(segments[i].experiment.n_samples for i in group)
        n = -(-n // multiple) * multiple
        for i in group:
            exp = segments[i].experiment
            signal = np.asarray(exp.signal)
            out[i] = dataclasses.replace(exp, signal=np.pad(signal, (0, n - signal.size), "edge"))
    return out


def replacements(plant, values: dict, xp=np) -> dict:
    """{name: value} of ``values`` as ``plant.replace`` takes them: vector elements
    (``f_track[2]``) gathered into their vectors (the plant's own where an element is not
    given, else each element's declared start); scalars pass through."""
    out, vectors = {}, {}
    for name, value in values.items():
        if "[" not in name:
            out[name] = value
            continue
        base, i = parameters.base_name(name), int(name[name.index("[") + 1 : -1])
        if base not in vectors:
            decl = plantspec.param(base)
            have = plant.get(base) if base in plant.param_names() else (decl.start,) * decl.size
            vectors[base] = list(have) if isinstance(have, tuple) else list(xp.asarray(have))
        vectors[base][i] = value
    for base, items in vectors.items():
        out[base] = (
            xp.stack([xp.asarray(v) for v in items])
            if xp is not np
            else tuple(float(v) for v in items)
        )
    return out


def positions(plants, controllers, experiments, full, layout, smoothing, shape: Shape, own=None):
    """The smooth positions [m] of every recording (a list, ``shape.lengths`` samples each;
    not finite where a run diverged) at the vector ``full`` of natural values laid out as
    ``layout``: recording i runs ``plants[i]`` with the values it reads
    (``layout.reads[i]``), ``controllers[i]`` and ``experiments[i]`` with its fitted start
    values (``layout.starts[i]``). ``own`` (recordings, shared values), a diagnosis's: 1 where
    a candidate frees recording i's own copy of shared value k, which it then reads instead of
    the shared one (one compiled program serves both kinds of candidate); None: every
    recording reads the entry its layout gives. A controller that reads whole counts reads the
    position's mean, y - q/2, and the position returned is that reading + q/2 (a position
    width of one count leaves 0.2 % of the staircase, which gives a Jacobian only at the count
    edges; the exact re-check reads whole counts)."""
    out = [None] * len(plants)
    for group in shape.groups:
        ps, exps = [], []
        for i in group:
            have = plants[i].param_names()
            values = {
                n: full[j] if own is None else jnp.where(own[i, k] > 0, full[j], full[k])
                for k, (n, j) in enumerate(layout.reads[i])
                if parameters.base_name(n) in have
            }
            ps.append(plants[i].replace(**replacements(plants[i], values, jnp)))
            starts = {v: full[j] for v, j in layout.starts[i]}
            exps.append(dataclasses.replace(experiments[i], **starts))
        q = shape.counts[group[0]]
        sm = dataclasses.replace(smoothing, position=q) if q > 0 else smoothing

        def run(plant, controller, exp, n_sub=shape.substeps[group[0]], sm=sm):
            return simulate_smooth(plant, controller, exp, smoothing=sm, substeps=n_sub).position

        ctrls = [controllers[i] for i in group]
        if len(group) == 1:
            pos = run(ps[0], ctrls[0], exps[0])[None]
        else:
            pos = jax.vmap(run)(*(_stacked(x) for x in (ps, ctrls, exps)))
        for lane, i in enumerate(group):
            out[i] = pos[lane, : shape.lengths[i]] + q / 2
    return out


def _stacked(trees):
    """The pytrees ``trees`` (one structure) stacked leaf by leaf along a new first axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *trees)
