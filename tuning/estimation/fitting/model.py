"""A fit's model of fixed structure: theta laid out as every fit's is
(:func:`tuning.estimation.engine.layout.for_fit`: the fitted parameters, then each recording's
start values), the smooth simulator's residuals and their Jacobian (forward mode,
several points in one batched, sharded program), and the exact simulator's runs
(:class:`_Problem`)."""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart import plantspec
from jaxcart.parallel import put, sharded_map
from jaxcart.smoothing import Smoothing
from jaxcart.substeps import substeps_per_sample
from jaxcart.workers import SERIAL
from tuning.estimation.engine import parameters, smooth_runs
from tuning.estimation.engine.exact_runs import ExactMemo, exact_position
from tuning.estimation.engine.layout import Layout, for_fit
from tuning.estimation.engine.least_squares import LM_DAMPING
from tuning.estimation.engine.noise import RecordingNoise, effective_samples
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.fitting.names import (
    _default_start,
    _element,
    canonical,
    default_start,
)


class Nuisance(NamedTuple):
    """A per-recording value fitted beside the plant: value = base + scale * theta, or, when
    ``bounded``, base + scale * sigmoid(theta) (within [base, base + scale]). name: "y0" [m] or
    "yd0" [m/s]."""

    name: str
    base: float
    scale: float
    bounded: bool = False

    def value(self, theta, xp=np):
        if self.bounded:
            return self.base + self.scale / (1 + xp.exp(-theta))
        return self.base + self.scale * theta

    def slope(self, theta) -> float:
        """d value / d theta."""
        if self.bounded:
            e = math.exp(-abs(float(theta)))
            return self.scale * e / (1 + e) ** 2
        return self.scale


#: Points per batched evaluation (every call is padded to a multiple: one compiled program):
#: the damping values one Levenberg-Marquardt iteration tries at once.
LM_BATCH = len(LM_DAMPING)
#: Bounded nuisance values stay within sigmoid(+-BOUNDED_LIMIT) of their range.
BOUNDED_LIMIT = 6.0
#: Segments are padded to a multiple of this many samples (fewer recompilations).
PAD = 256


class _Static(NamedTuple):
    """What the compiled residual function is specialised on (hashable: a jit static): theta's
    layout, each segment's start values' forms (:class:`Nuisance`, base 0: the bases are
    data) and the runs' :class:`~tuning.estimation.engine.smooth_runs.Shape`."""

    layout: Layout
    forms: tuple
    shape: smooth_runs.Shape


def _full(theta, bases, static: _Static):
    """The natural values [SI] of every entry of theta: a parameter's from its internal
    coordinate, a start value's through its :class:`Nuisance` form (its base a datum)."""
    lay = static.layout
    full = [None] * lay.size
    for starts, forms, base in zip(lay.starts, static.forms, bases, strict=True):
        for j, (form, (_, i)) in enumerate(zip(forms, starts, strict=True)):
            full[i] = form._replace(base=base[j]).value(theta[i], jnp)
    for i, name in enumerate(lay.names):
        if full[i] is None:
            full[i] = parameters.to_value(name, theta[i], jnp)
    return jnp.stack(full) if full else jnp.zeros(0)


def _positions(theta, data, smoothing, static: _Static):
    """Simulated positions of every segment (padded), concatenated [m]: the engine's
    :func:`~tuning.estimation.engine.smooth_runs.positions`. The start values' bases are data
    (a traced array), so that recordings differing only in them share one compilation."""
    plants, controllers, experiments, bases = (list(x) for x in zip(*data, strict=True))
    full = _full(theta, bases, static)
    pos = smooth_runs.positions(
        plants, controllers, experiments, full, static.layout, smoothing, static.shape
    )
    return jnp.concatenate(pos)


def _residuals_jacobian(theta, data, measured, weight, smoothing, static):
    """(r, dr/dtheta) of one theta: forward mode (a few parameters, many samples)."""
    TRACES[static] = TRACES.get(static, 0) + 1  # runs when traced, not when called

    def residuals(th):
        r = (_positions(th, data, smoothing, static) - measured) * weight
        return r, r

    jac, r = jax.jacfwd(residuals, has_aux=True)(theta)
    return r, jac


_BATCHED: dict = {}
#: How often the residual function was traced, per :class:`_Static` (tests: once).
TRACES: dict = {}


def _batched_residuals(static: _Static):
    """``run(thetas (K, m), data, measured, weight, smoothing) -> (r (K, n), J (K, n, m))``:
    one compiled program per :class:`_Static`, sharded over the devices (:mod:`jaxcart.parallel`).
    The CPU's per-step loop overhead dominates a single run, so K trial points cost little more
    than one."""
    if static not in _BATCHED:
        _BATCHED[static] = sharded_map(
            partial(_residuals_jacobian, static=static), name="fit-residuals", static=static
        )
    return _BATCHED[static]


_positions_jit = jax.jit(_positions, static_argnames="static")


class _Problem:
    """Segments, theta's layout and the compiled residual function."""

    def __init__(self, segments, params, settings, executor=None, given=()):
        self.segments = segments
        self.given = frozenset(given)  # the names whose start values the caller gave
        self.read: dict = {}  # start values read off the recordings (start_where_read)
        self.executor = executor or SERIAL
        # Each recording's run by its plant and start: a forward difference in one recording's
        # start (or its own drive limit) re-simulates that recording alone.
        self.memo = ExactMemo(executor=self.executor, run=exact_position)
        self.params = tuple(canonical(p) for p in params)
        self.n_params = len(self.params)
        self.settings = settings
        self.layout = layout = for_fit(self.params, segments)
        forms = tuple(tuple(v._replace(base=0.0) for v in s.nuisance) for s in segments)
        # The name of every entry of theta: the parameters, then each segment's start values.
        self.entries = list(layout.names)
        theta = [parameters.to_theta(p, self._start_value(p)) for p in self.params]
        theta += [
            0.0 if v.bounded else (getattr(seg.experiment, v.name) - v.base) / v.scale
            for seg in segments
            for v in seg.nuisance
        ]
        self.theta0 = np.asarray(theta, dtype=float)
        # Every segment padded to a multiple of PAD samples (weight 0 there): recordings of
        # nearly the same length then share one compiled residual function.
        plants = [s.plant for s in segments]
        n_subs = [
            substeps_per_sample(p) if settings.substeps is None else settings.substeps
            for p in plants
        ]
        shape = smooth_runs.shape_of(segments, plants, n_subs, side_by_side=False)
        experiments = smooth_runs.padded(segments, shape, PAD)
        padded = [e.n_samples for e in experiments]
        self.static = _Static(layout, forms, shape._replace(lengths=tuple(padded)))
        self.sizes = [s.target.size for s in segments]
        self.observed = np.concatenate([s.target for s in segments])
        # Several recordings: each against its own floor, as a diagnosis weighs them.
        self.noise = RecordingNoise(segments) if len(segments) > 1 else None
        # On the device once: host leaves would be transferred again at every evaluation.
        self.data = jax.tree.map(
            put,
            tuple(
                (s.plant, s.controller, e, np.asarray([v.base for v in s.nuisance], dtype=float))
                for s, e in zip(segments, experiments, strict=True)
            ),
        )
        self.measured = put(
            np.concatenate(
                [
                    np.pad(s.target, (0, n - s.target.size))
                    for s, n in zip(segments, padded, strict=True)
                ]
            )
        )
        self.weight = put(
            np.concatenate(
                [
                    np.pad(np.ones(s.target.size), (0, n - s.target.size))
                    for s, n in zip(segments, padded, strict=True)
                ]
            )
        )
        self.rows = np.concatenate(
            [
                np.arange(n) + off
                for n, off in zip(self.sizes, np.cumsum([0, *padded[:-1]]), strict=True)
            ]
        )

    def _start_value(self, p) -> float:
        k, base = parameters.recording_of(p), base_name(p)
        segs = self.segments if k is None else [self.segments[k]]
        i = _element(p.split("@")[0])
        values = [
            float(s.plant.get(base) if i is None else s.plant.get(base)[i])
            for s in segs
            if base in s.params or p in s.params
        ]
        value = values[0] if values else _default_start(p.split("@")[0])
        if parameters.is_log(p) and not value > 0:
            value = _default_start(p.split("@")[0])
        return value

    def start_source(self, p) -> str:
        """Where parameter ``p``'s start value comes from, in words (for a value held)."""
        base = base_name(p)
        declared = default_start().get(base)
        if p in self.read:
            where = "the recordings (the cart's equation of motion fitted to their moving samples)"
        elif base in self.given:
            where = "what the fit was given (the --plant file, or in jaxcart lab an earlier part)"
        elif base in plantspec.parameter_names() and plantspec.effect_of_param(base) is None:
            where = "the recordings' plant (the handout's appendix, a plant file or [plant])"
        elif declared is not None and math.isclose(
            self._start_value(p), declared if not isinstance(declared, tuple) else declared[0]
        ):
            where = "the effect's declared typical value"
        else:
            where = "the recordings' plant (a plant file or [plant])"
        return (
            f"its start value from {where}; give another in a plant file (--plant FILE) or "
            f"the recording's [plant] table ({base} = VALUE)"
        )

    def smoothing(self, width) -> Smoothing:
        return Smoothing(voltage=self.settings.voltage_width, velocity=width, position=1e-6)

    def evaluate(self, theta, width):
        """(r, J) over the recorded samples, numpy float64; r = inf where the simulation is not
        finite."""
        th = put(theta, float)
        if th.size == 0:
            r = _positions_jit(th, self.data, self.smoothing(width), self.static) - self.measured
            r = np.asarray(r)[self.rows]
            return r, np.zeros((r.size, 0))
        r, jac = self.evaluate_batch(th[None, :], width)
        return r[0], jac[0]

    def evaluate_batch(self, thetas, width):
        """(r (K, n), J (K, n, m)) of K points theta at once (one program, padded to
        :data:`LM_BATCH` points); r = inf for a point whose simulation is not finite."""
        thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
        k = thetas.shape[0]
        size = -(-k // LM_BATCH) * LM_BATCH
        padded = np.concatenate([thetas, np.repeat(thetas[-1:], size - k, axis=0)])
        r, jac = _batched_residuals(self.static)(
            put(padded, float), self.data, self.measured, self.weight, self.smoothing(width)
        )
        r, jac = np.asarray(r)[:k, self.rows], np.asarray(jac)[:k, self.rows]
        bad = ~(np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(jac), axis=(1, 2)))
        r[bad] = np.inf
        return r, jac

    def segment_values(self, theta, k):
        """(plant values {name: value}, nuisance {name: value}) of segment k at theta."""
        return (
            {p: float(parameters.to_value(p, theta[i])) for p, i in self.layout.reads[k]},
            {v.name: float(v.value(theta[i])) for v, i in self.nuisance_index(k)},
        )

    def theta_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of every entry of theta: the plant's values inside what a cart of this
        lab has (engine.parameters.bounds), each bounded nuisance within +-BOUNDED_LIMIT (its
        sigmoid keeps a slope there), the other nuisances free."""
        low = np.full(self.theta0.size, -np.inf)
        high = np.full(self.theta0.size, np.inf)
        for i, name in enumerate(self.params):
            low[i], high[i] = (parameters.to_theta(name, b) for b in parameters.bounds(name))
        for k in range(len(self.segments)):
            for v, i in self.nuisance_index(k):
                if v.bounded:
                    low[i], high[i] = -BOUNDED_LIMIT, BOUNDED_LIMIT
        return low, high

    def clip_bounded(self, theta, reset=False):
        """theta within :meth:`theta_bounds`, with ``reset`` each bounded nuisance at 0, the
        middle of its range."""
        theta = np.clip(np.asarray(theta, dtype=float), *self.theta_bounds())
        if reset:
            for k in range(len(self.segments)):
                for v, i in self.nuisance_index(k):
                    if v.bounded:
                        theta[i] = 0.0
        return theta

    def nuisance_index(self, k):
        """((Nuisance with its base, index in theta), ...) of segment k."""
        idx = [i for _, i in self.layout.starts[k]]
        return tuple(zip(self.segments[k].nuisance, idx, strict=True))

    def simulate_exact(self, theta):
        """Exact-simulator positions of each segment at theta (list of arrays) [m]."""
        return self.simulate_exact_many([theta])[0]

    def simulate_exact_many(self, thetas):
        """:meth:`simulate_exact` at each of ``thetas``: each recording's run made once for its
        plant and start (a memo), those not made yet several at a time (the executor's
        ``map``)."""
        jobs = []
        for theta in thetas:
            for k, seg in enumerate(self.segments):
                values, nuisance = self.segment_values(theta, k)
                plant = seg.plant.replace(**smooth_runs.replacements(seg.plant, values))
                exp = dataclasses.replace(seg.experiment, **nuisance)
                job = (plant, seg.controller, exp, seg.counts_in_loop)
                jobs.append(((k, plant, exp.y0, exp.yd0), job))
        self.memo.fill(jobs, list(self.sizes) * len(thetas))
        runs = [self.memo.segment(key, lambda job=job: exact_position(job)) for key, job in jobs]
        n = len(self.segments)
        return [runs[i : i + n] for i in range(0, len(runs), n)]

    def exact_residuals(self, theta):
        """Exact-simulator positions minus the measured ones, all segments [m]."""
        return np.concatenate(self.simulate_exact(theta)) - self.observed

    def exact_available(self) -> bool:
        """True when the exact simulator models every effect of every segment's plant."""
        try:
            self.simulate_exact(self.theta0)
        except (ImportError, NotImplementedError):
            return False
        return True

    def start_where_read(self, candidates) -> None:
        """Start at the one of ``candidates`` ({name: value} each, read off the recordings:
        :func:`~tuning.estimation.engine.starts.read_off_each`) whose smooth run has the lowest
        :meth:`objective` (an independent generator's tap beside a PD run held back by a 1 A
        current limit read B_eq 6.3 kg/s together, 1.49 from the tap, for 1.5)."""
        if not candidates:
            return
        thetas = np.repeat(self.theta0[None, :], len(candidates), axis=0)
        for theta, found in zip(thetas, candidates, strict=True):
            for name, value in found.items():
                theta[self.params.index(name)] = parameters.to_theta(name, value)
        best = 0
        if len(candidates) > 1:
            width = self.settings.widths[-1]
            rs = np.concatenate(
                [self.evaluate_batch(thetas[k : k + LM_BATCH], width)[0]
                 for k in range(0, len(thetas), LM_BATCH)]
            )  # fmt: skip
            best = int(np.argmin([self.objective(r)[0] for r in rs]))
        self.theta0, self.read = thetas[best], candidates[best]

    def objective(self, r) -> tuple:
        """(cost, row weights or None) of the residual ``r`` over every sample: one recording's
        r @ r; several recordings' :meth:`RecordingNoise.criterion
        <tuning.estimation.engine.noise.RecordingNoise.criterion>`, each against its own
        floor, with the weights of its reweighted least squares (with one recording it is a
        monotone function of r @ r: the same steps)."""
        if self.noise is None:
            return float(r @ r), None
        parts = self.split(r)
        return self.noise.criterion(parts), self.row_weights(parts)

    def row_weights(self, parts):
        """Each sample's weight in the joint least squares of several recordings at the
        residuals ``parts`` (one array per recording): its recording's."""
        w = self.noise.weights(parts)
        return np.concatenate([np.full(n, wk) for n, wk in zip(self.sizes, w, strict=True)])

    def sum_of_squares(self, r) -> float:
        """r @ r, or the weighted sum whose change is the :meth:`objective`'s to first order."""
        return float(r @ r) if self.noise is None else self.noise.sum_of_squares(self.split(r))

    def cost_per_variance(self, r) -> float:
        """How much the :meth:`objective` rises for a step of one standard error at ``r``
        (those that its effective samples support): sum of squares / n_eff."""
        return self.sum_of_squares(r) / effective_samples(self.split(r))

    def split(self, r):
        """Per-segment parts of a vector over all samples."""
        return np.split(np.asarray(r), np.cumsum(self.sizes)[:-1])
