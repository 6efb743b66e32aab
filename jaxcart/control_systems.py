"""The loop's linear part as python-control systems: plant, PID, closed loop, discrete and
continuous (docs/interop.md).

The discrete forms are the loop the hardware runs (docs/design.md, "The digital loop is the
truth"): the cart sampled with a zero-order hold at the controller's Ts, and the canonical PID
of :mod:`hw.control_law` exactly, with its state (the integral I_k and one derivative-filter
state), so ``control.forced_response`` of :func:`closed_loop` from :func:`initial_state` equals
:func:`jaxcart.simulate` of the same linear loop sample by sample. The continuous forms are
the textbook counterparts: C(s) = kp + ki/s + kd s/(tau s + 1).

Only the linear part: m y'' + c y' = gamma v (``Plant.m``, ``Plant.c``, ``Plant.gamma``), and a
``delay`` effect (exact in discrete time, a Pade approximant in continuous time). The other
effects (friction, amplifier limit, ...) and the software limit ``v_limit`` are left out, so the
systems describe the loop while |v| stays below the limit and friction is negligible. Units:
position [m], voltage [V], time [s].

Signals are named: the cart has input ``u`` [V], output ``y`` [m], states ``y``, ``y_dot``; the
PID has inputs ``r``, ``y`` [m], output ``u`` [V]; the closed loop input ``r`` and outputs
``y``, ``u`` (``loop["y", "r"]`` is position from reference).

>>> import jaxcart as jc
>>> loop = closed_loop(jc.handout_plant(), jc.PID(kp=40.0, kd=5.0, ki=5.0))
>>> loop.dt, loop.input_labels, loop.output_labels
(0.001, ['r'], ['y', 'u'])
>>> bool(max(abs(loop.poles())) < 1)
True
"""

from __future__ import annotations

import math

import control
import numpy as np

from jaxcart.errors import UserError
from jaxcart.plausibility import delayed_plant, plant_delay

#: Names of the systems (python-control prefixes interconnected states with them).
PLANT_NAME = "cart"
PID_NAME = "pid"


def _linear(plant) -> tuple[float, float, float]:
    """(m [kg], c [kg/s], gamma [N/V]) of the plant's linear part, as floats."""
    try:
        values = tuple(float(x) for x in (plant.m, plant.c, plant.gamma))
    except TypeError:
        raise UserError(
            "the plant holds a batch of parameter values; build the systems for one plant"
        ) from None
    if not all(math.isfinite(x) for x in values):
        raise UserError(f"plant m, c, gamma = {values}: every value must be finite")
    return values


def _gains(pid) -> dict:
    try:
        g = {k: float(getattr(pid, k)) for k in ("kp", "ki", "kd", "tau")}
    except TypeError:
        raise UserError("the PID holds a batch of gains; build the systems for one PID") from None
    bad = [k for k, v in g.items() if not math.isfinite(v)]
    if bad:
        raise UserError(f"PID {bad[0]} = {g[bad[0]]}: give a finite value")
    return g


def _ts(sample_time) -> float:
    ts = float(sample_time)
    if not (math.isfinite(ts) and ts > 0):
        raise UserError(f"sample_time = {sample_time!r} s: give a positive number of seconds")
    return ts


# ---------------------------------------------------------------- the cart


def plant_ss(plant, sample_time: float | None = None) -> control.StateSpace:
    """The cart m y'' + c y' = gamma u, position from voltage, states (y [m], y' [m/s]).

    Continuous without ``sample_time`` [s]; with it, the zero-order-hold discretization the
    hardware sees (``control.sample_system(..., 'zoh')``: exact for a voltage held over each
    sample). A ``delay`` effect (the one linear effect) is included: discrete, exactly (states
    u_1 ... u_L, the last L commands [V]; with delay = n Ts + s the motor sees u_{k-n-1} over
    the first s of the sample and u_{k-n} over the rest, as :mod:`jaxcart.effects.delay`);
    continuous, as a Pade approximant of order ``PADE_ORDER`` (states pade_1 ...)."""
    m, c, gamma = _linear(plant)
    a = np.array([[0.0, 1.0], [0.0, -c / m]])
    b = np.array([[0.0], [gamma / m]])
    names = dict(inputs="u", outputs="y", name=PLANT_NAME)
    delay = _delay(plant)
    if sample_time is None:
        if delay == 0:
            return control.ss(a, b, [[1.0, 0.0]], [[0.0]], states=["y", "y_dot"], **names)
        # The approximant of a unit delay, time-scaled by the delay: the coefficients of
        # pade(delay) span delay^order and lose digits for short delays.
        unit = control.ss(control.tf(*control.pade(1.0, PADE_ORDER)))
        pa, pb = unit.A / delay, unit.B / delay
        q = unit.nstates
        big_a = np.block([[a, b @ unit.C], [np.zeros((q, 2)), pa]])
        big_b = np.vstack([b @ unit.D, pb])
        states = ["y", "y_dot"] + [f"pade_{i + 1}" for i in range(q)]
        return control.ss(big_a, big_b, np.eye(1, 2 + q), [[0.0]], states=states, **names)
    ts = _ts(sample_time)
    if delay == 0:
        cont = control.ss(a, b, [[1.0, 0.0]], [[0.0]], states=["y", "y_dot"], **names)
        return control.sample_system(cont, ts, "zoh", name=PLANT_NAME)
    return _delayed_zoh(plant, ts, delay)


#: Order of the Pade approximant of a delay in continuous time.
PADE_ORDER = 6


def _delay(plant) -> float:
    """The plant's delay effect [s] as the simulators apply it (0 without one); other effects
    are not linear."""
    return plant_delay(plant)


def _delayed_zoh(plant, ts, delay):
    """The ZOH cart behind a delay line, exactly (:func:`jaxcart.plausibility.delayed_plant`:
    states y, y_dot, u_1 ... u_L, the last L commands)."""
    big_a, big_b = delayed_plant(plant, ts, delay)
    size = big_a.shape[0]
    states = ["y", "y_dot"] + [f"u_{j + 1}" for j in range(size - 2)]
    return control.ss(
        big_a,
        big_b[:, None],
        np.eye(1, size),
        [[0.0]],
        ts,
        states=states,
        inputs="u",
        outputs="y",
        name=PLANT_NAME,
    )


def plant_tf(plant, sample_time: float | None = None) -> control.TransferFunction:
    """P(s) = gamma / (m s^2 + c s) [m/V]; with ``sample_time`` [s] its ZOH form P(z); with a
    delay effect, the transfer function of :func:`plant_ss`."""
    if _delay(plant) != 0:
        sys = control.tf(plant_ss(plant, sample_time))
        return control.tf(sys.num, sys.den, sys.dt, inputs="u", outputs="y", name=PLANT_NAME)
    m, c, gamma = _linear(plant)
    sys = control.tf([gamma], [m, c, 0.0], inputs="u", outputs="y", name=PLANT_NAME)
    if sample_time is None:
        return sys
    return control.sample_system(sys, _ts(sample_time), "zoh", name=PLANT_NAME)


# ---------------------------------------------------------------- the PID


def _check_continuous(g) -> None:
    if g["kd"] != 0 and g["tau"] == 0:
        raise UserError(
            f"PID kd = {g['kd']:g} with tau = 0: the continuous derivative kd s is improper; "
            "give tau > 0 (Simulink's N = 1/tau) or use the discrete form"
        )


def controller_tf(pid, *, discrete: bool = True) -> control.TransferFunction:
    """The PID from error to command [V/m] (the feedback path), as the code runs it:

    discrete (Ts = ``pid.sample_time``): kp + ki Ts/(z - 1) + kd (z - 1)/((tau + Ts) z - tau)
    (forward-Euler integral, backward-Euler filtered derivative; :mod:`hw.control_law`);
    continuous: kp + ki/s + kd s/(tau s + 1). Terms with a zero gain are left out. With
    ``derivative_on = "measurement"`` the reference enters through kp + ki Ts/(z - 1) only
    (see :func:`controller_ss`)."""
    g = _gains(pid)
    if discrete:
        ts = _ts(pid.sample_time)
        z = control.tf([1.0, 0.0], [1.0], ts)
        integral = ts / (z - 1)
        derivative = (z - 1) / ((g["tau"] + ts) * z - g["tau"])
        one = control.tf([1.0], [1.0], ts)
    else:
        _check_continuous(g)
        s = control.tf([1.0, 0.0], [1.0])
        integral = 1 / s
        derivative = s / (g["tau"] * s + 1)
        one = control.tf([1.0], [1.0])
    total = g["kp"] * one
    if g["ki"] != 0:
        total = total + g["ki"] * integral
    if g["kd"] != 0:
        total = total + g["kd"] * derivative
    return control.tf(total.num, total.den, total.dt, inputs="e", outputs="u", name=PID_NAME)


def _pid_states(g) -> list[str]:
    """The controller states that act (a zero gain's state would leave a spurious pole)."""
    return (["I"] if g["ki"] != 0 else []) + (["f"] if g["kd"] != 0 else [])


def controller_ss(pid, *, discrete: bool = True) -> control.StateSpace:
    """The PID with inputs (r, y) [m] and output u [V] (the unlimited command v_k).

    The derivative acts on s = r - y (derivative on error) or s = -y (on measurement) through
    a low-pass state f [m], the same form in both times (a state whose gain is zero is left
    out; I is the integral of r - y [m s]):

    discrete, :mod:`hw.control_law` exactly: v_k = kp e_k + ki I_k + kd d_k with
    d_k = (s_k - f_k)/(tau + Ts), I_{k+1} = I_k + Ts e_k, f_{k+1} = (tau f_k + Ts s_k)/(tau + Ts)
    (f_k = s_{k-1} - tau d_{k-1}, which turns the code's recursion
    d_k = (tau d_{k-1} + s_k - s_{k-1})/(tau + Ts) into one state);
    continuous: v = kp e + ki I + kd (s - f)/tau with I' = e, f' = (s - f)/tau, i.e.
    kd s/(tau s + 1) on s.
    """
    g = _gains(pid)
    kp, ki, kd, tau = g["kp"], g["ki"], g["kd"], g["tau"]
    err = np.array([1.0, -1.0])  # e = r - y from (r, y)
    sig = np.array([1.0 if pid.derivative_on == "error" else 0.0, -1.0])  # s from (r, y)
    if discrete:
        dt = _ts(pid.sample_time)
        h = tau + dt
        # (A, B, C) per state: I_{k+1} = I_k + Ts e_k; f_{k+1} = (tau f_k + Ts s_k)/h and
        # kd d_k = kd (s_k - f_k)/h, whose s_k part is feedthrough.
        rows = {"I": (1.0, dt * err, ki), "f": (tau / h, dt / h * sig, -kd / h)}
        through = kd / h
    else:
        _check_continuous(g)
        dt, inv = 0, (1.0 / tau if kd != 0 else 0.0)
        # I' = e; f' = (s - f)/tau and kd (s - f)/tau.
        rows = {"I": (0.0, err, ki), "f": (-inv, inv * sig, -kd * inv)}
        through = kd * inv
    states = _pid_states(g)
    n = len(states)
    a, b, c = np.zeros((n, n)), np.zeros((n, 2)), np.zeros((1, n))
    for i, name in enumerate(states):
        a[i, i], b[i], c[0, i] = rows[name]
    d = (kp * err + through * sig)[None, :]
    return control.ss(a, b, c, d, dt, inputs=["r", "y"], outputs="u", states=states, name=PID_NAME)


# ---------------------------------------------------------------- the closed loop


def closed_loop(plant, pid, *, discrete: bool = True) -> control.StateSpace:
    """The closed loop from reference r [m] to position y [m] and command u [V].

    Discrete (the default): the ZOH cart at ``pid.sample_time`` with the PID of
    :func:`controller_ss`, the loop the hardware runs; continuous: the cart with the continuous
    PID. States: the cart's (``cart_y``, ``cart_y_dot``) then the PID's (``pid_I``, ...); start
    them with :func:`initial_state` to match :func:`jaxcart.simulate`."""
    ts = _ts(pid.sample_time) if discrete else None
    cart = plant_ss(plant, ts)
    return control.interconnect(
        [cart, controller_ss(pid, discrete=discrete)],
        inputs="r",
        outputs=["y", "u"],
        name="loop",
    )


def initial_state(loop, pid, *, r0: float, y0: float = 0.0, yd0: float = 0.0) -> np.ndarray:
    """The state vector of ``loop`` (a :func:`closed_loop` of ``pid``) at the first sample,
    as the simulator starts: cart at y0 [m], y0' = yd0 [m/s], I = 0, d_{-1} = 0 and
    s_{-1} = s_0 (no derivative kick at k = 0), i.e. the filter state f = s_0 settled on the
    first input (both times); no command before t = 0 (a delay line of zeros). r0: r(0) [m]."""
    s0 = (r0 - y0) if pid.derivative_on == "error" else -y0
    start = {f"{PLANT_NAME}_y": y0, f"{PLANT_NAME}_y_dot": yd0, f"{PID_NAME}_f": s0}
    return np.array([float(start.get(label, 0.0)) for label in loop.state_labels])


def closed_loop_poles(plant, pid, *, discrete: bool = True) -> np.ndarray:
    """Poles of :func:`closed_loop`: z (stable inside the unit circle) or s [1/s] (stable in
    the left half-plane)."""
    return np.asarray(closed_loop(plant, pid, discrete=discrete).poles())


def is_stable(plant, pid, *, discrete: bool = True) -> bool:
    """Whether the linear closed loop is asymptotically stable (every pole strictly inside)."""
    p = closed_loop_poles(plant, pid, discrete=discrete)
    return bool(np.all(np.abs(p) < 1.0)) if discrete else bool(np.all(p.real < 0.0))
