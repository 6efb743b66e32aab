"""Step-response metrics (MATLAB/python-control ``stepinfo`` conventions) and smooth surrogates.

For a step of size A = r_final - y_0:
    rise_time:          first time y reaches 90 % of the step minus first time it reaches 10 %
    settling_time:      time of the first sample after the last one with |y - r| > 2 % of |A|
                        (inf when the run ends outside the band)
    overshoot:          max(0, (max y - r) / A) * 100 [%]  (in the direction of the step)
    steady_state_error: |r - y| at the last sample [m]
    peak_voltage:       max |applied voltage| [V]
    saturation_time:    time the unlimited command spends beyond the voltage limit [s]

Three implementations, each tested against the others or against python-control:
``step_info`` (numpy, from a response), ``step_metrics`` (JAX, streamed through the simulation
without storing it: the fast path for grids) and ``smooth_*`` surrogates for losses.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart.params import voltage_limit
from jaxcart.smooth_sim import DIVERGED_POSITION, Response, loop

SETTLING_BAND = 0.02
# Two samples per loop iteration lets XLA fuse across them: ~1.4x faster on a CPU where loops
# run as one task per operation, as fast as one where they compile whole (jaxcart.xlaflags).
_UNROLL = 2
RISE_LIMITS = (0.1, 0.9)


class StepInfo(NamedTuple):
    """Metrics of one step response. Times in s, overshoot in %, error in m, voltage in V."""

    rise_time: float
    settling_time: float
    overshoot: float
    steady_state_error: float
    peak_voltage: float
    saturation_time: float
    diverged: bool

    def as_dict(self) -> dict:
        return {k: (bool(v) if k == "diverged" else float(v)) for k, v in self._asdict().items()}

    def meets(self, settling_time: float = 1.0, overshoot: float = 5.0) -> bool:
        """True when the response meets the specification (settling and overshoot bounds)."""
        return bool(
            (not self.diverged)
            and self.settling_time < settling_time
            and self.overshoot < overshoot
        )


def step_info(response: Response, *, v_limit: float = np.inf, band: float = SETTLING_BAND):
    """Exact metrics of one step response (numpy); ``v_limit`` [V] for saturation_time."""
    t = np.asarray(response.time, dtype=float)
    y = np.asarray(response.position, dtype=float)
    r = np.asarray(response.reference, dtype=float)
    v = np.asarray(response.voltage, dtype=float)
    ts = t[1] - t[0]
    if bool(response.diverged) or not np.all(np.isfinite(y)):
        inf = float("inf")
        return StepInfo(inf, inf, inf, inf, float(np.nanmax(np.abs(v))), inf, True)
    amplitude = r[-1] - y[0]
    if amplitude == 0:
        raise ValueError("step_info: the reference does not step (r_final equals y_0)")
    z = (y - y[0]) / amplitude
    lo, hi = RISE_LIMITS
    t10 = t[np.argmax(z >= lo)] if np.any(z >= lo) else np.inf
    t90 = t[np.argmax(z >= hi)] if np.any(z >= hi) else np.inf
    outside = np.nonzero(np.abs(y - r[-1]) > band * abs(amplitude))[0]
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] + 1 >= t.size:
        settling = np.inf
    else:
        settling = t[outside[-1] + 1] - t[0]
    overshoot = max(0.0, (z.max() - 1.0) * 100.0)
    if response.unlimited is not None:
        saturated = np.abs(np.asarray(response.unlimited, dtype=float)) > v_limit
    else:  # a recording: the command was limited already
        command = np.asarray(response.command, dtype=float)
        saturated = (np.abs(command) >= v_limit * (1 - 1e-9)) | (np.abs(v) >= v_limit * (1 - 1e-9))
    return StepInfo(
        rise_time=float(t90 - t10) if np.isfinite(t10) and np.isfinite(t90) else np.inf,
        settling_time=float(settling),
        overshoot=float(overshoot),
        steady_state_error=float(abs(r[-1] - y[-1])),
        peak_voltage=float(np.abs(v).max()),
        saturation_time=float(saturated.sum() * ts),
        diverged=False,
    )


# ---------------------------------------------------------------- streamed (JAX)


def step_metrics(plant, controller, experiment, *, smoothing=None, substeps=None):
    """:class:`StepInfo` of a closed-loop step, computed while simulating (JAX; vmap it).

    Nothing per-sample is stored, so a batch of runs keeps its working set in cache. Same
    definitions as :func:`step_info`. Use ``smoothing=jaxcart.EXACT_FORMS`` for hard clip.
    """
    init, step = loop(plant, controller, experiment, smoothing=smoothing, substeps=substeps)
    ts = experiment.sample_time
    n = experiment.n_samples
    r_final = experiment.signal[-1]
    amplitude = r_final - experiment.y0
    inv_amplitude = 1.0 / amplitude
    band = SETTLING_BAND * jnp.abs(amplitude)
    limit = voltage_limit(plant, controller)
    dtype = jnp.result_type(experiment.signal)
    inf = jnp.asarray(jnp.inf, dtype)
    # Speed (results bit for bit as with separate values). XLA:CPU computes every carried value
    # in a loop of its own, recomputing from the loop state what that value needs; so values
    # that need the same work ride together as one complex pair (one loop computes both): the
    # two voltage metrics share the controller's arithmetic, the others need only y_k. A
    # diverged run is one whose max |y_k| exceeds DIVERGED_POSITION or is NaN (max propagates
    # NaN), compared once at the end; a first crossing time is a running min of the sample
    # times where z is past the level. The last sample is taken outside the scan so y_{n-1}
    # needs no carry. W1 per CPU-second (2 cores, measured): 1.04-1.2x (float32), 1.1-1.2x
    # (float64) the former pairing (t10, t90), (peak, peak_v) + last_out, n_sat and a
    # diverged flag (loop body 251 -> 215 operations); that pairing was 2.0x separate values.
    pair = jax.lax.complex

    def update(acc, k, s):
        times, levels, volts, last_out = acc
        t10, t90, peak, y_max = times.real, times.imag, levels.real, levels.imag
        n_sat, peak_v = volts.real, volts.imag
        y = s.position
        z = (y - experiment.y0) * inv_amplitude
        tk = k * ts
        t10 = jnp.minimum(t10, jnp.where(z >= RISE_LIMITS[0], tk, inf))
        t90 = jnp.minimum(t90, jnp.where(z >= RISE_LIMITS[1], tk, inf))
        last_out = jnp.where(jnp.abs(y - r_final) > band, k, last_out)
        peak = jnp.maximum(peak, z)
        y_max = jnp.maximum(y_max, jnp.abs(y))
        n_sat = n_sat + (jnp.abs(s.unlimited) > limit)
        peak_v = jnp.maximum(peak_v, jnp.abs(s.voltage))
        return (pair(t10, t90), pair(peak, y_max), pair(n_sat, peak_v), last_out)

    def body(carry, xs):
        inner, acc = carry
        k, signal_k = xs
        inner, s = step(inner, signal_k)
        return (inner, update(acc, k, s)), None

    zero = jnp.zeros((), dtype)
    acc0 = (pair(inf, inf), pair(-inf, zero), pair(zero, zero), jnp.asarray(-1, jnp.int32))
    steps = jnp.arange(n, dtype=jnp.int32)
    carry = (init, acc0)
    carry, _ = jax.lax.scan(
        body, carry, (steps[: n - 1], experiment.signal[: n - 1]), unroll=_UNROLL
    )
    inner, acc = carry
    _, last = step(inner, experiment.signal[n - 1])
    times, levels, volts, last_out = update(acc, steps[n - 1], last)
    t10, t90, peak, y_max = times.real, times.imag, levels.real, levels.imag
    n_sat, peak_v = volts.real, volts.imag
    bad = ~(y_max <= DIVERGED_POSITION)
    y_last = last.position
    bad = bad | ~jnp.isfinite(y_last)
    return info_from_accumulated(
        t10, t90, last_out, n, ts, peak, r_final, y_last, peak_v, n_sat, bad
    )


def info_from_accumulated(
    t10, t90, last_out, n, ts, peak, r_final, y_last, peak_v, n_sat, bad
) -> StepInfo:
    """:class:`StepInfo` from a run's accumulated quantities: the 10 % and 90 % crossing times
    [s], the last sample index outside the band (-1: none) of n at sample time ts [s], the
    peak as a fraction of the step, the final reference and position [m], the peak voltage
    [V], the saturated samples and whether the run is bad (every metric inf then). Shared by
    the streamed step metrics here and the tuner's loss (tuning.design.losses)."""
    inf = jnp.inf
    settling = jnp.where(last_out < 0, 0.0, jnp.where(last_out + 1 >= n, inf, (last_out + 1) * ts))
    return StepInfo(
        rise_time=jnp.where(bad | (t90 == inf), inf, t90 - t10),
        settling_time=jnp.where(bad, inf, settling),
        overshoot=jnp.where(bad, inf, jnp.maximum(0.0, (peak - 1.0) * 100.0)),
        steady_state_error=jnp.where(bad, inf, jnp.abs(r_final - y_last)),
        peak_voltage=peak_v,
        saturation_time=n_sat * ts,
        diverged=bad,
    )
