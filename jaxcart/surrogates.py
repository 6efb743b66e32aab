"""Smooth, differentiable surrogates of the step metrics, for losses (tuning, fitting).

The exact metrics (:func:`jaxcart.metrics.step_info`, MATLAB ``stepinfo`` conventions) are built
from hard thresholds and a max, so their gradient is 0 or undefined. Here each hard piece is
replaced by a smooth one with a ``width``, expressed as a fraction of the step |A| (so the same
width means the same thing for a 1 cm and a 50 cm step). Every surrogate converges to its exact
metric as ``width -> 0`` (tests/test_surrogates.py), and is smooth for ``width > 0``:

- "sample k is outside the band" 1{|y_k - r| > band |A|} becomes a smooth step
  p_k = smooth_step((|z_k - 1| - band) / width), with z = (y - y_0) / A the normalized response;
  the step is a C1 cubic that is exactly 0 below -1 and exactly 1 above 1 (compact support:
  the thousands of settled samples contribute exactly nothing, where a logistic's tails would add
  up over a long horizon and bias the settling time by a large fraction);
- settling time = Ts * #{k : some j >= k is outside} becomes Ts * sum_k (1 - prod_{j>=k} (1 - p_j))
  (the expected count if the p_j were independent events), in log space so it cannot underflow;
- first crossing time of a level (rise time 10 % -> 90 %) becomes Ts * sum_k prod_{j<=k} (1 - p_j)
  with p_j = smooth_step((z_j - level) / width);
- max_k z_k becomes the softmax-weighted mean of z (temperature = width), which approaches the max
  from below with an error of order width (no log(n) bias as a log-sum-exp would have), and
  max(0, x) becomes (x + sqrt(x^2 + width^2)) / 2;
- |e| becomes sqrt(e^2 + (width |A|)^2).

A wider surrogate also leaves a margin: a peak that comes within a few widths of the band edge
already counts as partly outside, so a loss built on it keeps away from the edge.

All functions work on the last axis of arrays of shape (..., n_samples) (vmap-friendly).

>>> import jaxcart as jc
>>> res = jc.simulate(jc.handout_plant(), jc.PID(kp=100.0, kd=8.0, v_limit=6.0), jc.step(0.5))
>>> info = smooth_step_info(res, width=1e-4)
>>> round(float(info.settling_time), 2), round(float(jc.step_info(res).settling_time), 2)
(0.85, 0.85)
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcart.metrics import RISE_LIMITS, SETTLING_BAND

#: Default width [fraction of the step]: 1e-3 is 0.5 mm on the lab's 0.5 m step.
DEFAULT_WIDTH = 1e-3


class SmoothStepInfo(NamedTuple):
    """Smooth surrogates of :class:`jaxcart.StepInfo`'s step metrics (JAX arrays).

    rise_time [s], settling_time [s], overshoot [%], steady_state_error [m].
    The settling time of a run that ends outside the band is about the horizon plus one sample
    (finite, so that a loss keeps a gradient; the exact metric is inf there).
    """

    rise_time: jax.Array
    settling_time: jax.Array
    overshoot: jax.Array
    steady_state_error: jax.Array


def _normalized(position, reference):
    """(z, A): z = (y - y_0) / A with A = r_final - y_0 the step, on the last axis."""
    y = jnp.asarray(position)
    r = jnp.asarray(reference)
    y0 = y[..., :1]
    amplitude = r[..., -1:] - y0
    return (y - y0) / amplitude, amplitude[..., 0]


def _sample_time(time):
    t = jnp.asarray(time)
    return t[..., 1] - t[..., 0]


def smooth_step(x):
    """0 for x <= -1, 1 for x >= 1, the C1 cubic 3 s^2 - 2 s^3 of s = (x + 1) / 2 between."""
    s = jnp.clip(0.5 * (x + 1.0), 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _log_not(p):
    """log(1 - p), clamped at log(eps) where p = 1 (so a certain event costs a finite amount)."""
    eps = jnp.finfo(jnp.result_type(p)).eps
    return jnp.log1p(-jnp.minimum(p, 1.0 - eps))


def smooth_relu(x, width):
    """max(x, 0) smoothed over ``width`` (algebraic: (x + sqrt(x^2 + width^2)) / 2)."""
    return 0.5 * (x + jnp.sqrt(x * x + width * width))


def soft_max(x, width, axis=-1):
    """max of ``x`` along ``axis``, smoothed: the softmax-weighted mean at temperature ``width``.

    Below the max by at most ``width * log(n)`` and, for a smooth peak sampled finely, by about
    ``width / 2``; equal to it as ``width -> 0``.
    """
    weights = jax.nn.softmax(x / width, axis=axis)
    return jnp.sum(weights * x, axis=axis)


def overshoot(position, reference, *, width=DEFAULT_WIDTH):
    """Smooth overshoot [%]: 100 * max(0, max z - 1), z = (y - y_0) / (r_final - y_0)."""
    z, _ = _normalized(position, reference)
    return 100.0 * smooth_relu(soft_max(z, width) - 1.0, width)


def settling_time(time, position, reference, *, width=DEFAULT_WIDTH, band=SETTLING_BAND):
    """Smooth settling time [s]: time after which |y - r_final| stays within ``band`` |A|.

    Converges to ``step_info``'s (first sample after the last one outside the band, measured
    from time[0]) as ``width -> 0``; about horizon + Ts when the run ends outside the band.
    """
    z, _ = _normalized(position, reference)
    distance = jnp.abs(z - 1.0) - band
    # log(1 - p_j); its reverse cumulative sum is log P(every sample from k on is inside).
    log_inside = _log_not(smooth_step(distance / width))
    log_inside_from = jax.lax.cumsum(log_inside, axis=log_inside.ndim - 1, reverse=True)
    outside_later = -jnp.expm1(log_inside_from)
    return _sample_time(time) * jnp.sum(outside_later, axis=-1)


def crossing_time(time, position, reference, level, *, width=DEFAULT_WIDTH):
    """Smooth time [s, from time[0]] at which z = (y - y_0) / A first reaches ``level``."""
    z, _ = _normalized(position, reference)
    log_below = _log_not(smooth_step((z - level) / width))
    not_yet = jnp.exp(jax.lax.cumsum(log_below, axis=log_below.ndim - 1))
    return _sample_time(time) * jnp.sum(not_yet, axis=-1)


def rise_time(time, position, reference, *, width=DEFAULT_WIDTH, limits=RISE_LIMITS):
    """Smooth rise time [s]: first reaching 90 % of the step minus first reaching 10 %."""
    lo, hi = limits
    return crossing_time(time, position, reference, hi, width=width) - crossing_time(
        time, position, reference, lo, width=width
    )


def band_excess(time, position, reference, *, after, band=SETTLING_BAND):
    """Mean distance outside the settling band after time ``after`` [s, from time[0]], in
    units of the band (0 when the response stays inside from ``after`` on).

    The constraint "settling time < after" says exactly that this is 0. Unlike the settling
    surrogate, it keeps a gradient where the response is far outside the band until the end
    (a slow integral creep, a cart stuck short of the target), where the settling time is
    flat at the horizon.
    """
    z, _ = _normalized(position, reference)
    t = jnp.asarray(time)
    late = (t - t[..., :1]) >= after
    outside = jax.nn.relu(jnp.abs(z - 1.0) - band) / band
    count = jnp.maximum(jnp.sum(late, axis=-1), 1)
    return jnp.sum(jnp.where(late, outside, 0.0), axis=-1) / count


def steady_state_error(position, reference, *, width=DEFAULT_WIDTH):
    """Smooth |r - y| at the last sample [m] (sqrt(e^2 + (width A)^2))."""
    _, amplitude = _normalized(position, reference)
    e = jnp.asarray(reference)[..., -1] - jnp.asarray(position)[..., -1]
    w = width * amplitude
    return jnp.sqrt(e * e + w * w)


def smooth_step_info(
    response=None,
    *,
    time=None,
    position=None,
    reference=None,
    width=DEFAULT_WIDTH,
    band=SETTLING_BAND,
) -> SmoothStepInfo:
    """All four surrogates, from a :class:`jaxcart.Response` or from time/position/reference.

    width: smoothing width as a fraction of the step (a JAX array is fine: changing it does not
    retrace); band: settling band as a fraction of the step (2 %).
    """
    if response is not None:
        time, position, reference = response.time, response.position, response.reference
    if time is None or position is None or reference is None:
        raise ValueError("smooth_step_info needs a response or time, position and reference")
    return SmoothStepInfo(
        rise_time=rise_time(time, position, reference, width=width),
        settling_time=settling_time(time, position, reference, width=width, band=band),
        overshoot=overshoot(position, reference, width=width),
        steady_state_error=steady_state_error(position, reference, width=width),
    )
