"""The peers of workload W1 (tuning/benchmark/workload.py): the same loop written without
jaxcart's simulator, one run at a time in python-control and scipy, a batch at a time in numpy.

They share nothing with jaxcart's simulator but the control law (hw.control_law, the code the
hardware runs): the plant step is the exact zero-order hold computed here with
scipy.linalg.expm (python-control, numpy; the C kernel reads the same matrices) or integrated
by solve_ivp, and the metrics are computed here in numpy (:func:`trace_metrics`, the
definitions of ``jaxcart.step_metrics``).
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import control
import numpy as np
import scipy.linalg
from scipy.integrate import solve_ivp

from hw.control_law import PIDState, pid_init, pid_update
from jaxcart.effects import Held, Saturation
from jaxcart.params import voltage_limit

#: solve_ivp tolerances: scipy's defaults. A 1 ms interval is 1/80 of the plant's time constant
#: m/c: the traces stay within ~4e-13 m of the exact-hold reference over 3 s at these
#: tolerances as at rtol 1e-9 (measured), which only costs time (~2x) and would flatter jaxcart.
IVP_RTOL, IVP_ATOL = 1e-3, 1e-6


def zoh_matrices(plant, ts: float):
    """Exact zero-order-hold step of m y'' + c y' = gamma u over ts [s]: x+ = Ad x + Bd u with
    x = (y [m], y' [m/s]), from the matrix exponential of the augmented system (not jaxcart's
    closed forms)."""
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    aug = np.zeros((3, 3))
    aug[0, 1] = 1.0
    aug[1, 1] = -c / m
    aug[1, 2] = gamma / m
    e = scipy.linalg.expm(aug * ts)
    return e[:2, :2], e[:2, 2]


def _voltage_stages(plant):
    """The plant's exact voltage effects (an amplifier saturation, a deadzone) as one numpy
    function; the W1 peers model a linear plant with memoryless voltage effects only."""
    other = [e for e in plant.effects if e.stage != "voltage" or e.splits_sample]
    if other:
        names = ", ".join(type(e).name for e in other)
        raise ValueError(
            f"the W1 peers model a linear plant with memoryless voltage effects; not {names}"
        )
    stages = plant.stage("voltage")

    def apply(u):
        for effect in stages:
            u = effect.exact((), Held(u, u, 0.0), 0.0)[0].late
        return u

    return apply


def _limit(plant, controller) -> float:
    """The voltage limit [V] the saturation time counts against (jaxcart's definition)."""
    return float(voltage_limit(plant, controller))


def trace_metrics(
    y, unlimited, applied, *, r_final: float, y0: float, ts: float, limit: float
) -> dict:
    """Step metrics of one trace (numpy), the definitions of ``jaxcart.step_metrics``.

    y: positions y_k [m]; unlimited: PID output v_k [V]; applied: voltage at the motor [V];
    r_final [m], y0 [m], ts [s]; limit: the voltage limit [V] for saturation_time.
    """
    y = np.asarray(y, dtype=float)
    n = y.size
    amplitude = r_final - y0
    bad = not np.all(np.abs(y) <= 1e3)
    z = (y - y0) / amplitude
    inf = math.inf

    def first(mask):
        return float(np.argmax(mask)) * ts if mask.any() else inf

    out = np.nonzero(np.abs(y - r_final) > 0.02 * abs(amplitude))[0]
    settling = 0.0 if out.size == 0 else (inf if out[-1] + 1 >= n else (out[-1] + 1) * ts)
    info = {
        # inf when the run never reaches 90 % (the peak is monotone: 90 % implies 10 %)
        "rise_time": first(z >= 0.9) - first(z >= 0.1) if (z >= 0.9).any() else inf,
        "settling_time": settling,
        "overshoot": max(0.0, (z.max() - 1.0) * 100.0),
        "steady_state_error": abs(r_final - y[-1]),
        "peak_voltage": float(np.abs(applied).max()),
        "saturation_time": float(np.count_nonzero(np.abs(unlimited) > limit)) * ts,
        "diverged": bad,
    }
    if bad:
        info.update(rise_time=inf, settling_time=inf, overshoot=inf, steady_state_error=inf)
    return info


# ---------------------------------------------------------------- peer: python-control


def python_control_run(plant, controller, experiment, gains):
    """One W1 run as a discrete-time ``control.nlsys`` (dt = Ts) whose update is the PID, the
    clips and the exact ZOH plant step; returns (positions [m], metrics dict).

    States: y [m], y' [m/s], the PID memory (I, d, s_prev) and the last v_k, u_k [V] (kept as
    states so the response carries them). One extra sample gives v and u at the last sample.
    """
    ts = experiment.sample_time
    pid = dataclasses.replace(
        controller, kp=float(gains[0]), kd=float(gains[1]), ki=float(gains[2])
    )
    ad, bd = zoh_matrices(plant, ts)
    voltage = _voltage_stages(plant)

    def update(t, x, u, params):
        state = PIDState(x[2], x[3], x[4])
        command, unlimited, state = pid_update(pid, state, u[0], x[0], xp=np)
        applied = voltage(command)
        plant_next = ad @ x[:2] + bd * applied
        return [
            plant_next[0],
            plant_next[1],
            state.integral,
            state.derivative,
            state.previous,
            unlimited,
            applied,
        ]

    r = np.asarray(experiment.signal, dtype=float)
    n = r.size
    sys_ = control.nlsys(update, None, inputs=["r"], states=7, dt=ts, name="w1")
    t = np.arange(n + 1) * ts
    y0, yd0 = float(experiment.y0), float(experiment.yd0)
    init = pid_init(pid, r[0], y0, xp=np)
    x0 = [y0, yd0, init.integral, init.derivative, init.previous, 0.0, 0.0]
    resp = control.input_output_response(sys_, t, np.append(r, r[-1]), x0, t_eval=t)
    x = resp.states
    y = x[0, :n]
    info = trace_metrics(
        y, x[5, 1:], x[6, 1:], r_final=float(r[-1]), y0=y0, ts=ts, limit=_limit(plant, pid)
    )
    return y, info


# ---------------------------------------------------------------- peer: scipy


def scipy_run(plant, controller, experiment, gains, *, rtol=IVP_RTOL, atol=IVP_ATOL):
    """One W1 run: at each sample the PID (hw.control_law) computes u_k, then ``solve_ivp``
    integrates the continuous plant over the hold interval; returns (positions, metrics)."""
    ts = experiment.sample_time
    pid = dataclasses.replace(
        controller, kp=float(gains[0]), kd=float(gains[1]), ki=float(gains[2])
    )
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    voltage = _voltage_stages(plant)

    def rhs(t, x, u):
        return [x[1], (gamma * u - c * x[1]) / m]

    r = np.asarray(experiment.signal, dtype=float)
    n = r.size
    y0 = float(experiment.y0)
    x = np.array([y0, float(experiment.yd0)])
    state = pid_init(pid, r[0], y0, xp=np)
    y, unlimited, applied = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        y[k] = x[0]
        command, unlimited[k], state = pid_update(pid, state, r[k], x[0], xp=np)
        applied[k] = voltage(command)
        if k + 1 < n:
            sol = solve_ivp(
                rhs, (k * ts, (k + 1) * ts), x, args=(applied[k],), rtol=rtol, atol=atol
            )
            x = sol.y[:, -1]
    info = trace_metrics(
        y, unlimited, applied, r_final=float(r[-1]), y0=y0, ts=ts, limit=_limit(plant, pid)
    )
    return y, info


# ---------------------------------------------------------------- peer: vectorized numpy


def numpy_batch(plant, controller, experiment, gains, *, dtype=np.float64, record: int = 0):
    """W1 for a batch of gains (rows kp, kd, ki) in numpy: the same recursion on arrays, time
    loop in Python, in-place updates, metrics streamed (nothing per sample is stored).

    Returns (metrics dict of arrays, positions of the first ``record`` runs, shape (record, n)).
    The exact ZOH step uses the structure of this plant (Ad[0, 0] = 1, Ad[1, 0] = 0).
    """
    c = _numpy_constants(plant, controller, experiment, dtype)
    s = _numpy_state(gains, c, dtype, record)
    n = c.r.size
    for k in range(n):
        if record:
            s.trace[:, k] = s.y[:record]
        _numpy_pid(s, c, c.r[k])
        _numpy_metrics_step(s, c, k)
        if k + 1 < n:  # the plant step is skipped after the last sample
            _numpy_plant_step(s, c)
    return _numpy_metrics(s, c, n), s.trace


def _numpy_constants(plant, controller, experiment, dtype) -> SimpleNamespace:
    """The numbers of W1's loop in ``dtype``: the ZOH step (a01 [s], a11, b0 [m/V], b1 [m/(s
    V)]), the limits [V], the PID filter's keep and gain, the reference and metric scales."""
    if controller.derivative_on != "error" or controller.anti_windup != "none":
        raise ValueError("the numpy peer implements W1's PID: derivative on error, no anti-windup")
    ts = experiment.sample_time
    ad, bd = zoh_matrices(plant, ts)
    if ad[0, 0] != 1.0 or ad[1, 0] != 0.0:
        raise ValueError("the numpy peer assumes a plant without a position-dependent force")
    f = np.dtype(dtype).type
    sat = [float(e.v_sat) for e in plant.effects if isinstance(e, Saturation)]
    tau, inv = float(controller.tau), 1.0 / (float(controller.tau) + ts)
    r = np.asarray(experiment.signal, dtype=float).astype(dtype)
    amplitude = float(r[-1]) - float(experiment.y0)
    return SimpleNamespace(
        ts=ts,
        a01=f(ad[0, 1]),
        a11=f(ad[1, 1]),
        b0=f(bd[0]),
        b1=f(bd[1]),
        v_lim=f(controller.v_limit),
        v_sat=f(min(sat, default=math.inf)),
        limit=f(_limit(plant, controller)),
        keep=f(tau * inv),
        gain=f(inv),
        r=r,
        r_final=f(r[-1]),
        y0=f(experiment.y0),
        yd0=f(experiment.yd0),
        inv_amp=f(1.0 / amplitude),
        band=f(0.02 * abs(amplitude)),
    )


def _numpy_state(gains, c: SimpleNamespace, dtype, record: int) -> SimpleNamespace:
    """The batch's arrays: gains, plant and PID state, scratch, and the streamed metrics."""
    b = gains.shape[0]
    kp, kd, ki = (np.ascontiguousarray(gains[:, i], dtype=dtype) for i in range(3))
    e, v, u, tmp = (np.empty(b, dtype) for _ in range(4))
    n10, n90, n_sat = (np.zeros(b, np.int32) for _ in range(3))
    return SimpleNamespace(
        kp=kp,
        kd=kd,
        ki=ki,
        y=np.full(b, c.y0, dtype),
        yd=np.full(b, c.yd0, dtype),
        integral=np.zeros(b, dtype),
        deriv=np.zeros(b, dtype),
        prev=np.full(b, c.r[0] - c.y0, dtype),
        e=e,
        v=v,
        u=u,
        tmp=tmp,
        peak=np.full(b, -np.inf, dtype),
        peak_v=np.zeros(b, dtype),
        max_abs=np.zeros(b, dtype),
        n10=n10,
        n90=n90,
        n_sat=n_sat,
        last_out=np.full(b, -1, np.int32),
        mask=np.empty(b, bool),
        trace=np.empty((record, c.r.size), dtype),
    )


def _numpy_pid(s: SimpleNamespace, c: SimpleNamespace, r_k) -> None:
    """The PID (hw.control_law.pid_update, derivative on error) and the two clips, in place."""
    tmp = s.tmp
    np.subtract(r_k, s.y, out=s.e)
    np.subtract(s.e, s.prev, out=tmp)
    tmp *= c.gain
    s.deriv *= c.keep
    s.deriv += tmp
    np.multiply(s.kp, s.e, out=s.v)
    np.multiply(s.ki, s.integral, out=tmp)
    s.v += tmp
    np.multiply(s.kd, s.deriv, out=tmp)
    s.v += tmp
    np.clip(s.v, -c.v_lim, c.v_lim, out=s.u)
    np.clip(s.u, -c.v_sat, c.v_sat, out=s.u)
    np.multiply(s.e, c.ts, out=tmp)
    s.integral += tmp
    s.prev, s.e = s.e, s.prev


def _numpy_metrics_step(s: SimpleNamespace, c: SimpleNamespace, k: int) -> None:
    """Streamed metrics of y_k. The running peak makes "first k with z_k >= 0.1" a count."""
    tmp, mask = s.tmp, s.mask
    np.subtract(s.y, c.y0, out=tmp)
    tmp *= c.inv_amp
    np.maximum(s.peak, tmp, out=s.peak)
    np.less(s.peak, 0.1, out=mask)
    s.n10 += mask
    np.less(s.peak, 0.9, out=mask)
    s.n90 += mask
    np.subtract(s.y, c.r_final, out=tmp)
    np.abs(tmp, out=tmp)
    np.greater(tmp, c.band, out=mask)
    np.copyto(s.last_out, k, where=mask)
    np.abs(s.v, out=tmp)
    np.greater(tmp, c.limit, out=mask)
    s.n_sat += mask
    np.abs(s.u, out=tmp)
    np.maximum(s.peak_v, tmp, out=s.peak_v)
    np.abs(s.y, out=tmp)
    np.maximum(s.max_abs, tmp, out=s.max_abs)  # NaN propagates: marks the run diverged


def _numpy_plant_step(s: SimpleNamespace, c: SimpleNamespace) -> None:
    """Exact ZOH step of the plant, in place."""
    tmp = s.tmp
    np.multiply(s.yd, c.a01, out=tmp)
    s.y += tmp
    np.multiply(s.u, c.b0, out=tmp)
    s.y += tmp
    s.yd *= c.a11
    np.multiply(s.u, c.b1, out=tmp)
    s.yd += tmp


def _numpy_metrics(s: SimpleNamespace, c: SimpleNamespace, n: int) -> dict:
    """The step metrics of the batch from the streamed counts (dict of arrays)."""
    bad = ~(s.max_abs <= 1e3)
    inf, ts, last_out = np.inf, c.ts, s.last_out
    settling = np.where(last_out < 0, 0.0, np.where(last_out + 1 >= n, inf, (last_out + 1) * ts))
    return {
        # inf when 90 % is never reached (n90 < n implies n10 <= n90: the peak is monotone)
        "rise_time": np.where(bad | (s.n90 >= n), inf, (s.n90 - s.n10) * ts),
        "settling_time": np.where(bad, inf, settling),
        "overshoot": np.where(bad, inf, np.maximum(0.0, (s.peak.astype(float) - 1.0) * 100.0)),
        "steady_state_error": np.where(bad, inf, np.abs(float(c.r_final) - s.y.astype(float))),
        "peak_voltage": s.peak_v.astype(float),
        "saturation_time": s.n_sat * ts,
        "diverged": bad,
    }
