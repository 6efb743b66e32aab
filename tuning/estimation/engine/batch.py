"""Batched fits of candidate structures: one superset plant, one sharded Levenberg-Marquardt step.

Every candidate structure is the same pytree: a *superset* plant that holds every candidate
effect (delay, deadzone, saturation, Coulomb, stiction, spring, current limit), each one neutral
(delay 0, deadzone 0, v_sat = i_max = 1e4, f_c = f_s = k_s = 0) where the candidate lacks it. A
candidate is a vector of index slots into one full parameter vector (its free parameters; unused
slots point at a dummy entry) and a base vector (the neutral or start values). One compiled
Levenberg-Marquardt step (Jacobian in forward mode: a few parameters, one tangent each, and the
values of different recordings' own sharing one: :meth:`BatchFitter._colouring`) is mapped over
the candidates (:func:`jaxcart.parallel.sharded_map`: sharded over every local device); every
recording of a joint diagnosis is simulated inside it
(one plant, each file's controller), so the same compiled step serves every round.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart.parallel import devices, sharded_map
from jaxcart.plantspec import build_plant
from jaxcart.smoothing import Smoothing
from jaxcart.substeps import substeps_per_sample
from tuning.distributed import gather_rows
from tuning.estimation.engine import parameters, smooth_runs
from tuning.estimation.engine.layout import DUMMY, for_candidates
from tuning.estimation.engine.least_squares import State, compiled_marquardt

#: Voltage smoothing width at the widest stage [V] (narrowing with the others).
VOLTAGE_WIDTH = 4e-3


def _superset(plant, shared):
    """``plant`` with every ``shared`` parameter it lacks at its neutral stand-in (a drive
    effect is not added to a plant without its motor: a tap)."""
    have = plant.param_names()
    missing = {k: parameters.stand_in(k) for k in shared if k not in have}
    if not plant.motor_connected:
        missing = {k: v for k, v in missing.items() if not parameters.is_drive(k)}
    return build_plant(missing, base=plant, check=False)


def _owner(name: str) -> int:
    """The recording a slot acts in alone (``v_sat@2``, ``y0@0``: 2, 0), else -1."""
    return parameters.recording_of(name) if "@" in name else -1


def _colours(owners) -> list[int]:
    """A colour for each slot of ``owners`` (the recording it acts in alone, -1 for all):
    each shared slot its own, a recording's own slots the first colour without a slot of
    the same recording (and no shared one)."""
    out, groups = [], []  # groups: the recordings of each colour (None: a shared slot's)
    for rec in owners:
        k = next(
            (k for k, g in enumerate(groups) if rec >= 0 and g is not None and rec not in g),
            len(groups),
        )
        if k == len(groups):
            groups.append(None if rec < 0 else set())
        if rec >= 0:
            groups[k].add(int(rec))
        out.append(k)
    return out


def _theta_arrays(layout):
    """(log mask, linear scale, lower and upper bounds in internal units) of every slot."""
    names = layout.names
    log_mask = np.array([n != DUMMY and parameters.is_log(n) for n in names])
    ranges = [parameters.bounds(n) if n != DUMMY else (-1e9, 1e9) for n in names]
    lo = np.array([parameters.to_theta(n, r[0]) for n, r in zip(names, ranges, strict=True)])
    hi = np.array([parameters.to_theta(n, r[1]) for n, r in zip(names, ranges, strict=True)])
    scale = np.array(
        [
            1.0 if m or n == DUMMY else parameters.value_slope(n, 1.0)
            for n, m in zip(names, log_mask, strict=True)
        ]
    )
    return log_mask, scale, lo, hi


def _lm_trial(residuals, lo, hi, row_segment, noise=None):
    """The batched LM's step for one candidate, ``step(theta, lam, cost, jac, r, idx, free,
    base, own, seeds, support, width)`` -> (theta, lam, cost, jac, r): one ask and tell of the
    engine's :func:`~tuning.estimation.engine.least_squares.compiled_marquardt` from the
    accepted values theta, whose residual r and Jacobian jac are carried. The trial's residual
    and Jacobian come from one forward pass, and a trial that is kept brings its Jacobian for
    the next step (a rejected one costs no second pass at theta). A carried cost of inf asks
    for theta itself (a fit's first step at a width). Forward mode, one tangent per colour (see
    :meth:`BatchFitter._colouring`): slots that act on different recordings share a tangent,
    and each column is read back on its own recordings' rows (``row_segment``: the recording
    of every residual row). ``lo``, ``hi``: bounds of every slot, internal units.

    ``noise``: (nu, floor) per recording, the effective samples and the floor of the scaled
    residual's sum of squares: the cost is then sum_k nu_k log(SSE_k + floor_k) (each
    recording against its own level, :class:`~tuning.estimation.engine.noise.RecordingNoise`)
    and each step weighs a recording's rows by nu_k / (SSE_k + floor_k) at theta (iteratively
    reweighted least squares); None: the plain sum of squares."""

    def objective(r):
        if noise is None:
            return r @ r, jnp.ones_like(r)
        nu, floor = noise
        sse = jax.ops.segment_sum(r * r, row_segment, num_segments=nu.shape[0])
        weights = nu / (sse + floor)
        return jnp.sum(nu * jnp.log(sse + floor)), weights[row_segment] / jnp.max(weights)

    def step(theta, lam, cost, jac, r, idx, free, base, own, seeds, support, width):
        solver = compiled_marquardt(bounds=(lo[idx], hi[idx]), free=free, objective=objective)
        state = State(theta, r, jac, cost, lam)
        trial = solver.ask(state)[0]

        def push(t):
            return jax.jvp(lambda th: residuals(th, idx, base, own, width), (trial,), (t,))

        r_new, packed = jax.vmap(push, out_axes=(None, 1))(seeds)
        colour = jnp.argmax(seeds, axis=0)
        jac_new = packed[:, colour] * support[row_segment, :] * free[None, :]
        state = solver.tell(state, trial[None], r_new[None], jac_new[None])
        return state.x, state.damping, state.cost, state.jac, state.r

    return step


class BatchFitter:
    """The compiled, vmapped LM step for a set of segments (built once per diagnosis)."""

    def __init__(
        self,
        segments,
        start_plants,
        substeps: int | None = None,
        per_recording=(),
        compress=True,
        max_shared: int | None = None,
        noise=None,
    ):
        """``compress``: False gives every slot a tangent of its own (the plain forward-mode
        Jacobian, which the tests compare :meth:`_colouring`'s with). ``max_shared``: the most
        shared values any problem will free (a search's largest structure): the step is then
        compiled once, for the most tangents any problem can need. A second program for a
        search that grows costs more than the tangents a first round leaves unused (real P 50:
        17.3 s -> 13.7 s cold, 11.6 -> 10.9 s warm; joint five 40.1 -> 35.3 s cold; the lab,
        whose first round explains its recordings, 1.5 s more). ``noise``: a
        :class:`~tuning.estimation.engine.noise.RecordingNoise` of the segments: several
        recordings are then fitted each against its own level (see :func:`_lm_trial`);
        None: plain least squares."""
        self.segments = segments
        self.layout = layout = for_candidates(segments, per_recording)
        # The recording each slot acts in alone (-1: every recording, a shared value).
        self._owner = np.array([_owner(n) for n in layout.names], dtype=np.int32)
        self._n_colours = 0  # none compiled yet
        self._compress = compress
        # The most tangents a problem can need: its shared values, and a recording's own slots
        # (per-recording copies, a tap's start state) at most one colour each.
        own = [len(layout.own(i)) for i in range(len(segments))]
        self._most = None if max_shared is None else max_shared + max(own, default=0)
        self.supers = supers = [_superset(plant, layout.shared) for plant in start_plants]
        targets = [jnp.asarray(s.target) for s in segments]
        scale = 1.0 / math.sqrt(sum(s.target.size for s in segments))
        self.log_mask, scale_v, lo, hi = _theta_arrays(layout)
        log_mask_j, scale_j = jnp.asarray(self.log_mask), jnp.asarray(scale_v)
        lo_j, hi_j = jnp.asarray(lo), jnp.asarray(hi)
        base_smoothing = Smoothing()
        n_subs = [
            substeps_per_sample(sup, screening=True) if substeps is None else substeps
            for sup in supers
        ]
        self.shape = shape = smooth_runs.shape_of(segments, supers, n_subs)
        experiments = smooth_runs.padded(segments, shape)
        controllers = [s.controller for s in segments]

        def full_values(theta, idx, base):
            vals = jnp.where(log_mask_j[idx], jnp.exp(theta), theta * scale_j[idx])
            return base.at[idx].set(vals)

        def residuals(theta, idx, base, own, width):
            full = full_values(theta, idx, base)
            # Velocity and position widths follow the continuation; the voltage corners stay
            # narrow (as in tuning.estimation.fit): a rounded software limit misplaces a saturated
            # run.
            smoothing = base_smoothing.scaled(width)
            smoothing = dataclasses.replace(smoothing, voltage=VOLTAGE_WIDTH * width / 4.0)
            pos = smooth_runs.positions(
                supers, controllers, experiments, full, layout, smoothing, shape, own
            )
            # A run that diverged: a finite, far miss (the step is then rejected).
            out = [
                jnp.where(jnp.isfinite(y), y, 1.0) - t for y, t in zip(pos, targets, strict=True)
            ]
            return jnp.concatenate(out) * scale

        # The recording of every sample (a column's support is its slot's recordings).
        row_segment = np.concatenate(
            [np.full(s.target.size, i, dtype=np.int32) for i, s in enumerate(segments)]
        )
        weighing = None
        if noise is not None and len(segments) > 1:
            floor_sse = noise.sizes * noise.floors**2 * scale**2  # in the scaled residual's units
            weighing = (jnp.asarray(noise.n_eff), jnp.asarray(floor_sse))
        step = _lm_trial(residuals, lo_j, hi_j, row_segment, weighing)

        # One candidate per item, the width shared; sharded over every local device.
        run = sharded_map(lambda item, width: step(*item, width), cache=False)
        self._step = lambda *item, width: run(item, width)
        self._jnp = jnp

    def base_vector(self, values: dict) -> np.ndarray:
        """The full vector (natural units) from {name: value}; a per-recording copy takes the
        shared value where it is not given; neutral elsewhere."""
        base = np.zeros(self.layout.size)
        for j, n in enumerate(self.layout.names):
            k = parameters.base_name(n)
            if n in values:
                base[j] = values[n]
            elif k in values and k in self.layout.shared:
                base[j] = values[k]
            elif k in self.layout.shared:
                # A drive parameter on recordings without their motor (taps only) acts
                # nowhere: its stand-in value.
                sup = next((p for p in self.supers if k in p.param_names()), None)
                base[j] = parameters.stand_in(k) if sup is None else float(np.asarray(sup.get(k)))
        for i, starts in enumerate(self.layout.starts):
            exp = self.segments[i].experiment
            for v, j in starts:
                base[j] = values.get(f"{v}@{i}", getattr(exp, v))
        return base

    def fit(self, problems, widths, iterations, progress=None, kmax=None, share=None):
        """LM on every problem at once. problems: list of (free names, start values dict,
        base values dict). Returns list of (values dict, smooth mean square residual [m^2],
        jac, r).

        share: a :class:`tuning.distributed.Exchange` of a jax.distributed run: this process fits
        its :meth:`~tuning.distributed.Exchange.items` of the problems and every process gets
        every result (each problem's LM is independent of the others)."""
        jnp = self._jnp
        lay = self.layout
        kmax = max([len(p[0]) for p in problems] + [kmax or 0])
        idx = np.full((len(problems), kmax), lay.dummy, dtype=np.int32)
        free = np.zeros((len(problems), kmax))
        theta = np.zeros((len(problems), kmax))
        base = np.zeros((len(problems), lay.size))
        shared = lay.shared
        own = np.zeros((len(problems), len(self.segments), len(shared)))
        for c, (names, start, base_vals) in enumerate(problems):
            for i in range(len(self.segments)):
                own[c, i] = [f"{n}@{i}" in names for n in shared]
            base[c] = self.base_vector({**base_vals, **start})
            for s, n in enumerate(names):
                j = lay.index(n)
                idx[c, s] = j
                free[c, s] = 1.0
                theta[c, s] = parameters.to_theta(n, base[c, j])
        n = len(problems)
        rows = np.arange(n) if share is None else np.asarray(share.items(n), dtype=int)
        if rows.size == 0:  # more processes than problems: this one only gathers
            return self._gathered(share, problems, {}, progress, widths)
        n_mine = rows.size
        # A whole number of problems per device (copies of the first), so that the sharded
        # map neither pads nor cuts the batch, nor so reshards it, at each step: eager
        # operations on the carried Jacobian, split unevenly over the devices, made XLA abort
        # (seen in 2 of 6 runs of tests/test_new_effect.py two at a time), and in a
        # distributed run a resharded output opens a cross-process (gloo) channel for what is
        # a local computation.

        rows = np.concatenate([rows, np.repeat(rows[:1], -n_mine % len(devices()))])
        seeds, support = self._colouring(idx, free)
        seeds, support = jnp.asarray(seeds[rows]), jnp.asarray(support[rows])
        theta = jnp.asarray(theta[rows])
        lam = jnp.full(rows.size, 1e-2)
        idx_j, free_j, base_j = jnp.asarray(idx[rows]), jnp.asarray(free[rows]), base[rows]
        own_j = jnp.asarray(own[rows])
        base_j = jnp.asarray(base_j)
        n_rows = sum(seg.target.size for seg in self.segments)
        # (the step's own dtype: a carry of another would compile the step a second time)
        jac = jnp.zeros((rows.size, n_rows, kmax), dtype=theta.dtype)
        r = jnp.zeros((rows.size, n_rows), dtype=theta.dtype)
        for width, its in zip(widths, iterations, strict=True):
            lam = jnp.maximum(lam, 1e-3)
            # The residual and Jacobian at the values so far, at this width; then the trials.
            cost = jnp.full(rows.size, jnp.inf, dtype=theta.dtype)
            for _ in range(its + 1):
                theta, lam, cost, jac, r = self._step(
                    theta,
                    lam,
                    cost,
                    jac,
                    r,
                    idx_j,
                    free_j,
                    base_j,
                    own_j,
                    seeds,
                    support,
                    width=width,
                )
            if progress and share is None:
                progress(width, np.sum(np.asarray(r)[:n_mine] ** 2, axis=1))
        if share is not None:
            arrays = {k: np.asarray(v)[:n_mine] for k, v in dict(theta=theta, jac=jac, r=r).items()}
            return self._gathered(share, problems, arrays, progress, widths)
        return self._unpack(problems, theta, jac, r)

    def _colouring(self, idx, free):
        """(seeds (problems, colours, slots), support (problems, recordings, slots)) of the
        compressed forward-mode Jacobian (Curtis, Powell and Reid): a value free per
        recording (``v_sat@2``) or a tap's start state moves one recording's samples alone,
        so such values of different recordings share one tangent (a colour); a shared value
        has one of its own. The Jacobian is the same (each sample's derivative in a colour
        comes from the one slot of its recording there); the step's forward passes go from
        the slots (every copy of every recording) to the colours (the shared values, and the
        most any one recording has of its own). The number of colours is the most any problem
        can need from the first fit on (``max_shared``; else what the fits so far needed), and
        only grows, so a round does not compile the step again for fewer."""
        n, kmax = idx.shape
        recordings = np.arange(len(self.segments))
        colours = np.zeros((n, kmax), dtype=np.int32)
        support = np.zeros((n, len(self.segments), kmax))
        for c in range(n):
            slots = np.flatnonzero(free[c])
            owners = self._owner[idx[c, slots]]
            colours[c, slots] = _colours(owners) if self._compress else range(len(slots))
            for s, rec in zip(slots, owners, strict=True):
                support[c, :, s] = 1.0 if rec < 0 else recordings == rec
        need = int(colours.max()) + 1
        if need > self._n_colours:
            self._n_colours = max(need, self._most or 0)
        seeds = np.zeros((n, self._n_colours, kmax))
        for c in range(n):
            slots = np.flatnonzero(free[c])
            seeds[c, colours[c, slots], slots] = 1.0
        return seeds, support

    def _gathered(self, share, problems, arrays, progress, widths):
        """Every process's rows of a distributed fit, assembled (see :meth:`fit`)."""
        n = len(problems)
        parts = share.allgather({k: np.asarray(v) for k, v in arrays.items()})
        # A process without problems sent nothing.
        owners = [o for o, p in zip(share.owners(n), parts, strict=True) if p]
        full = gather_rows([p for p in parts if p], owners, n)
        if progress:  # only the final costs are gathered: one line, at the last width
            progress(widths[-1], np.sum(np.asarray(full["r"]) ** 2, axis=1))
        return self._unpack(problems, full["theta"], full["jac"], full["r"])

    def _unpack(self, problems, theta, jac, r):
        theta = np.asarray(theta)
        out = []
        for c, (names, _start, _b) in enumerate(problems):
            vals = {}
            for s, n in enumerate(names):
                vals[n] = float(parameters.to_value(n, float(theta[c, s])))
            res = np.asarray(r[c])
            out.append((vals, float(res @ res), np.asarray(jac[c]), res))
        return out
