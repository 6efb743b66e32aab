"""The tuning loss: smooth step metrics of the smoothed simulator, against the specification.

Gains are optimized in log space (theta = log gain), which keeps them positive and makes a step
of the optimizer a relative change (kp = 40 and kd = 5 move alike). For one gain set and one
plant, with the smooth surrogates Ts~ (settling time) and OS~ (overshoot) of
:mod:`jaxcart.surrogates`:

    loss = Ts~ / T_max + weight * ( relu(OS~ / OS_max - target) + relu(Ts~ / T_max - target)
                                     + E(target T_max) )

where E(t0) is the mean distance outside the settling band after t0, in band units
(:func:`jaxcart.surrogates.band_excess`): it keeps a gradient where the run never settles.

The hinge terms (an exact penalty: large slope, zero inside) dominate while the specification
is not met, so the optimizer first makes the gains feasible, then the first term drives the
settling time down toward the physical limit. ``target`` < 1 leaves a margin, because the smooth
model and the exact one differ slightly. Robust tuning takes a soft maximum of the loss over a
set of plants (softmax-weighted mean, :func:`jaxcart.surrogates.soft_max`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcart.accumulators import accumulate, value_and_jacfwd_rows
from jaxcart.errors import UserError
from jaxcart.metrics import RISE_LIMITS, SETTLING_BAND, StepInfo, info_from_accumulated
from jaxcart.params import voltage_limit
from jaxcart.smooth_sim import DIVERGED_POSITION, loop, simulate_smooth
from jaxcart.smoothing import Smoothing
from jaxcart.surrogates import (
    SmoothStepInfo,
    _log_not,
    band_excess,
    smooth_relu,
    smooth_step,
    smooth_step_info,
    soft_max,
)

#: Gain order of every array of gains in tuning (as in jaxcart.batch_metrics): kp, kd, ki.
GAIN_NAMES = ("kp", "kd", "ki")
#: Every number of the PID the tuner can free, in the order of its parameter vector: the
#: gains, then the derivative filter tau [s], the back-calculation gain kb [1/s] and the
#: software voltage limit v_limit [V] (the numeric fields of hw.control_law.PID).
PARAM_NAMES = GAIN_NAMES + ("tau", "kb", "v_limit")


@dataclass(frozen=True)
class Spec:
    """The design problem (the lab's by default).

    step: reference step [m]; settling_time: bound on the 2 % settling time [s];
    overshoot: bound on the overshoot [%]; band: settling band [fraction of the step];
    horizon: simulated time [s], long enough that a slow integral creep shows (default the
        larger of 3 s and 3 x settling_time)
    """

    step: float = 0.5
    settling_time: float = 1.0
    overshoot: float = 5.0
    band: float = SETTLING_BAND
    horizon: float | None = None

    def __post_init__(self):
        if self.horizon is None and isinstance(self.settling_time, float | int):
            object.__setattr__(self, "horizon", max(3.0, 3.0 * float(self.settling_time)))
        for name in ("settling_time", "overshoot", "band", "horizon"):
            value = getattr(self, name)
            if not (isinstance(value, float | int) and value > 0):
                raise UserError(f"spec {name} = {value!r}: it must be a positive number")
        if not (isinstance(self.step, float | int) and self.step != 0):
            raise UserError(f"spec step = {self.step!r} m: it must be a nonzero number")
        if self.horizon <= self.settling_time:
            raise UserError(
                f"spec horizon = {self.horizon} s must exceed the settling bound "
                f"{self.settling_time} s (use about 3x)"
            )


@dataclass(frozen=True)
class LossSettings:
    """Weights and widths of the loss (the continuation scales the widths).

    weight: slope of the hinge penalties (per unit of the normalized metric)
    target: fraction of each bound the smooth metrics aim under (margin for the exact model)
    width: surrogate width at scale 1 [fraction of the step]
    smoothing: simulator widths at scale 1 (voltage [V], velocity [m/s], position [m])
    robust_width: temperature of the soft maximum over plants [units of the loss]
    """

    weight: float = 10.0
    target: float = 0.9
    width: float = 4e-3
    smoothing: Smoothing = Smoothing(voltage=0.2, velocity=5e-3, position=1e-5)
    robust_width: float = 0.02


def gains_from_theta(theta, fixed, free_mask):
    """Parameters (order :data:`PARAM_NAMES`, or its first three: the gains) from their logs
    ``theta`` (free entries) and ``fixed`` values (the rest)."""
    return jnp.where(free_mask, jnp.exp(theta), fixed)


def controller_with(controller, gains):
    """``controller`` with its numbers from ``gains``: kp, kd, ki (3 entries) or every entry of
    :data:`PARAM_NAMES` (6)."""
    names = PARAM_NAMES[: len(gains)]
    return dataclasses.replace(controller, **{n: gains[i] for i, n in enumerate(names)})


def params_of(controller) -> tuple[float, ...]:
    """The controller's numbers in :data:`PARAM_NAMES` order."""
    return tuple(float(getattr(controller, n)) for n in PARAM_NAMES)


def plant_loss(
    gains, plant, controller, experiment, spec: Spec, settings: LossSettings, scale, substeps=None
):
    """(loss, SmoothStepInfo) of one gain set (kp, kd, ki) on one plant, at continuation
    ``scale`` (widths = scale x their values in ``settings``)."""
    smoothing = settings.smoothing.scaled(scale)
    response = simulate_smooth(
        plant,
        controller_with(controller, gains),
        experiment,
        smoothing=smoothing,
        substeps=substeps,
    )
    info = smooth_step_info(response, width=settings.width * scale, band=spec.band)
    ts = info.settling_time / spec.settling_time
    os = info.overshoot / spec.overshoot
    # Where the run never settles, the settling surrogate is flat at the horizon: the band
    # excess after the settling bound still says which way is in.
    excess = band_excess(
        response.time,
        response.position,
        response.reference,
        after=settings.target * spec.settling_time,
        band=spec.band,
    )
    penalty = jax.nn.relu(os - settings.target) + jax.nn.relu(ts - settings.target) + excess
    loss = ts + settings.weight * penalty
    # A run that blew up gets a large finite loss (its gradient is discarded by the caller).
    loss = jnp.where(response.diverged | ~jnp.isfinite(loss), 1e3, loss)
    return loss, info


class LossInfo(NamedTuple):
    """The smooth metrics a streaming loss sees: settling_time [s], overshoot [%] (the
    surrogates of :mod:`jaxcart.surrogates`), excess (band excess after target x T_max, in band
    units), steady_state_error [m], diverged; metrics: the exact step metrics
    (:class:`jaxcart.metrics.StepInfo`, hard thresholds) of the same smooth run, counted in the
    same loop (no derivative: they track which iterate is best)."""

    settling_time: jax.Array
    overshoot: jax.Array
    excess: jax.Array
    steady_state_error: jax.Array
    diverged: jax.Array
    metrics: StepInfo


def stream_loss(
    gains, plant, controller, experiment, spec: Spec, settings: LossSettings, scale, substeps=None
):
    """(loss, LossInfo): :func:`plant_loss`'s loss, summed inside the simulation loop.

    Same surrogates, no stored trace (tests/test_losses.py holds it to plant_loss). The
    settling surrogate Ts sum_k (1 - prod_{j>=k} (1 - p_j)) runs backwards in time; with
    P_k = sum_{j<k} log(1 - p_j) it is Ts (n - exp(P_n) sum_k exp(-P_k)), and the sum is kept
    as a running log-sum-exp (stable: -P_k only grows). The soft maximum of the overshoot is an
    online softmax (running max, rescaled sums).
    """
    smoothing = settings.smoothing.scaled(scale)
    width = settings.width * scale
    band = spec.band
    after = settings.target * spec.settling_time
    r_final = experiment.signal[-1]
    dtype = jnp.result_type(experiment.signal, float)
    late_count = jnp.maximum(jnp.sum((experiment.time - experiment.time[0]) >= after), 1)

    pid = controller_with(controller, gains)
    limit = voltage_limit(plant, pid)
    inf = jnp.asarray(jnp.inf, dtype)
    # y0: the first sample as the controller reads it, known before the loop (one more step,
    # outside it), so 1 / (r_final - y0) is loop-invariant rather than carried.
    start, first = loop(plant, pid, experiment, smoothing=smoothing, substeps=substeps)
    y0 = first(start, experiment.signal[0])[1].position
    lo = jnp.asarray(RISE_LIMITS, dtype)
    v_max = jax.lax.stop_gradient(limit)

    # Two groups of accumulators, not fifteen scalars: XLA on a CPU computes every carried
    # array in its own pass over the loop body (its tangents in another), each recomputing
    # what it depends on. ``soft`` (with tangents) is a tuple that accumulate packs into one
    # vector where that pays (no force effects); ``hard`` (without) is one vector.
    def update(acc, k, tk, s):
        soft, hard = acc
        p, lse, peak, den, num, excess, _ = soft
        # StepInfo's counters (as jaxcart.metrics.step_metrics) and the divergence flag, on
        # values without tangents: t10, t90, top, peak |v|, saturated samples, last sample
        # outside the band, bad (0/1).
        y, u, v = (jax.lax.stop_gradient(x) for x in (s.position, s.unlimited, s.voltage))
        zh = (y - experiment.y0) / (r_final - experiment.y0)
        t_rise = jnp.where((hard[:2] == inf) & (zh >= lo), tk, hard[:2])
        out = jnp.abs(y - r_final) > band * jnp.abs(r_final - experiment.y0)
        hard = jnp.concatenate(
            [
                t_rise,
                jnp.maximum(hard[2:4], jnp.stack([zh, jnp.abs(v)])),
                (hard[4] + (jnp.abs(u) > v_max))[None],
                jnp.where(out, k.astype(dtype), hard[5])[None],
                jnp.maximum(hard[6], ~(jnp.abs(y) <= DIVERGED_POSITION))[None],
            ]
        )
        z = (s.position - y0) / (r_final - y0)
        distance = jnp.abs(z - 1.0) - band
        lse = jnp.logaddexp(lse, -p)
        p = p + _log_not(smooth_step(distance / width))
        top = jnp.maximum(peak, z)
        fade = jnp.exp((peak - top) / width)
        w = jnp.exp((z - top) / width)
        den, num = den * fade + w, num * fade + z * w
        excess = excess + jnp.where(tk >= after, jax.nn.relu(distance) / band, 0.0)
        soft = (p, lse, top, den, num, excess, s.position)
        return soft, hard

    zero = jnp.zeros((), dtype)
    soft0 = (zero, zero, -inf, zero - 1e30, zero, zero, zero)
    hard0 = jnp.asarray([jnp.inf, jnp.inf, -jnp.inf, 0.0, 0.0, -1.0, 0.0], dtype)
    soft, hard = accumulate(
        plant,
        pid,
        experiment,
        (soft0, hard0),
        update,
        smoothing=smoothing,
        substeps=substeps,
    )
    p, lse, _, den, num, excess, y_last = soft
    t10, t90, top, peak_v, n_sat, last_out, bad = (hard[i] for i in range(7))
    bad = bad > 0
    n = experiment.n_samples
    ts_s = experiment.sample_time * (n - jnp.exp(p + lse))
    os_pct = 100.0 * smooth_relu(num / den - 1.0, width)
    excess = excess / late_count
    e = r_final - y_last
    sse = jnp.sqrt(e * e + (width * (r_final - y0)) ** 2)
    bad = bad | ~jnp.isfinite(y_last)
    ts = ts_s / spec.settling_time
    os = os_pct / spec.overshoot
    penalty = jax.nn.relu(os - settings.target) + jax.nn.relu(ts - settings.target) + excess
    loss = ts + settings.weight * penalty
    loss = jnp.where(bad | ~jnp.isfinite(loss), 1e3, loss)
    y_end = jax.lax.stop_gradient(y_last)
    metrics = info_from_accumulated(
        t10, t90, last_out, n, experiment.sample_time, top, r_final, y_end, peak_v, n_sat, bad
    )
    return loss, LossInfo(ts_s, os_pct, excess, sse, bad, metrics)


def make_loss(
    controller,
    experiment,
    spec: Spec,
    settings: LossSettings,
    *,
    robust: bool,
    substeps=None,
    stream: bool = True,
):
    """loss(theta, fixed, free_mask, plants, scale) -> (loss, aux) for one start.

    theta: log parameters (3: the gains, or 6: :data:`PARAM_NAMES`; entries where
    ``free_mask`` is False are ignored); fixed: the values used where ``free_mask`` is False;
    scale: continuation factor of the widths. ``plants`` is one Plant (aux: LossInfo, or
    SmoothStepInfo with ``stream=False``), or for robust tuning a Plant whose leaves carry a
    leading axis of plant samples: the loss is then the soft maximum over them (aux: (per-plant
    loss, info per plant)). Everything but the static configuration is an argument, so one
    compiled function serves every start, bound and continuation stage. ``stream``: the loss
    summed inside the loop (:func:`stream_loss`) rather than from a stored response
    (:func:`plant_loss`); the same number.
    """
    per_plant = stream_loss if stream else plant_loss

    def one(theta, fixed, free_mask, plant, scale):
        gains = gains_from_theta(theta, fixed, free_mask)
        return per_plant(
            gains, plant, controller, experiment, spec, settings, scale, substeps=substeps
        )

    if not robust:
        return one

    def worst(theta, fixed, free_mask, plants, scale):
        losses, infos = jax.vmap(one, in_axes=(None, None, None, 0, None))(
            theta, fixed, free_mask, plants, scale
        )
        return soft_max(losses, settings.robust_width), (losses, infos)

    return worst


def batched_value_and_jacfwd(loss):
    """Loss and gradient w.r.t. the free entries of theta for a batch of starts, by forward
    mode (one tangent per free parameter, the loss summed inside the loop: a few forward runs'
    cost, nothing stored). ``(theta (S, P), free (F,) int indices, fixed, free_mask, plants,
    scale) -> (losses (S,), aux, grad (S, P))``; the number F of free entries is static, their
    indices are not (other free sets of the same size reuse the compiled function)."""

    def of_free(u, theta, free, fixed, free_mask, plants, scale):
        return loss(theta.at[free].set(u), fixed, free_mask, plants, scale)

    grads = value_and_jacfwd_rows(of_free, has_aux=True)

    def run(theta, free, fixed, free_mask, plants, scale):
        (values, aux), g = grads(theta[:, free], theta, free, fixed, free_mask, plants, scale)
        return values, aux, jnp.zeros_like(theta).at[:, free].set(g)

    return run


__all__ = [
    "GAIN_NAMES",
    "PARAM_NAMES",
    "Spec",
    "LossInfo",
    "stream_loss",
    "params_of",
    "batched_value_and_jacfwd",
    "LossSettings",
    "SmoothStepInfo",
    "gains_from_theta",
    "controller_with",
    "plant_loss",
    "make_loss",
]
