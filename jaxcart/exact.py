"""The exact (verification) simulator: hard clip and event-exact Karnopp stick-slip, no smoothing.

Written independently of :mod:`jaxcart.simulate` (no shared integration code) so that it can check
it: the smooth simulator converges to this one as its widths go to 0 (tests/test_exact.py). Only
the control law (:mod:`hw.control_law`, written once by design) and the plant's parameters are
shared.

The sampled-data loop (sample time Ts [s], samples at t_k = k Ts):

    r_k --> [PID, software limit] --u_k--> [voltage effects: Saturation.exact] --v_k--> ZOH
      y_k ^                                                                              |
          '---------------- cart: m y'' + c y' = gamma v_k - f sgn(y') <-----------------'

Over one sample the drive F = gamma v_k [N] is constant, and within a slip phase so is the
friction -f_k sgn(y') [N]; the motion y'' = -a y' + b (a = c/m [1/s], b [m/s^2]) is then solved
in closed form (exponential and its phi functions via expm1, series for small a t, so c = 0 is
exact too). Stick-slip events are found in closed form (Karnopp, static level f_s >= kinetic f_k):

    start of sample, or velocity just reached 0 at time t* (closed form):
                      |
              y' == 0 ?  --no-->  slip, s = sgn(y'):  b = (F - s f_k)/m
                 | yes                |
                 v                    |  does y' reach 0 before the sample ends?
          |F| <= f_s ?                |    (only if s b < 0; t* = log1p(-a y'/b)/a)
          |yes       |no              |-- yes: advance to t*, set y' = 0 exactly, loop back up
          v          v                '-- no: advance to the sample end; done
        stuck:     slip, s = sgn(F)
        y' = 0 and y constant for the rest of the sample (F is constant until the next sample)

A velocity that starts at exactly 0 stays exactly 0 while stuck (no chatter); rounding can never
flip the sign of a velocity within a slip phase (it is clamped to 0, which the next sample's stick
test then resolves). At most two events happen in one sample; the loop allows more.

>>> from jaxcart import PID, handout_plant, step
>>> res = simulate_exact(handout_plant(f_c=1.0), PID(kp=20.0, v_limit=6.0), step(0.5))
>>> res.position.shape, res.diverged
((3001,), False)
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hw.control_law import PID, PIDState, pid_init, pid_update
from jaxcart.effects import Coulomb, Saturation
from jaxcart.errors import UserError
from jaxcart.experiments import Experiment
from jaxcart.metrics import StepInfo, step_info
from jaxcart.params import Plant
from jaxcart.simulate import DIVERGED_POSITION, Response

#: Voltage-stage effects with an exact memoryless form ``exact(v)`` [V -> V] modelled here.
EXACT_VOLTAGE_EFFECTS = (Saturation,)
#: Force-stage effects that are dry friction, ``friction_levels() -> (kinetic, static)`` [N].
EXACT_FRICTION_EFFECTS = (Coulomb,)
_SUPPORTED = EXACT_VOLTAGE_EFFECTS + EXACT_FRICTION_EFFECTS
#: Safety cap on stick-slip events per sample (the physics allows at most 2).
_MAX_EVENTS = 8
#: Below this a t the phi2 closed form cancels; a Taylor series is used instead.
_SERIES_BELOW = 0.5
#: Taylor coefficients of (x - 1 + e^{-x}) / x^2 = sum_n (-x)^n / (n + 2)!, enough for 1e-17 at
#: x = 0.5.
_PHI2_SERIES = tuple((-1.0) ** n / math.factorial(n + 2) for n in range(16))


# ---------------------------------------------------------------- closed forms


def _phis(a: float, t: float) -> tuple[float, float, float]:
    """e^{-a t}, phi1 = (1 - e^{-a t})/a and phi2 = (t - phi1)/a [s, s^2], for a >= 0.

    Over a phase of length t with y'' = -a y' + b:  y'(t) = e y'_0 + phi1 b,
    y(t) = y_0 + phi1 y'_0 + phi2 b.  Exact at a = 0 (phi1 = t, phi2 = t^2/2).
    """
    x = a * t
    if x == 0.0:
        return 1.0, t, 0.5 * t * t
    em = -math.expm1(-x)  # 1 - e^{-x}, accurate for small x
    if x < _SERIES_BELOW:
        g = 0.0
        for coef in reversed(_PHI2_SERIES):
            g = g * x + coef
    else:
        g = (x - em) / (x * x)
    return 1.0 - em, t * em / x, t * t * g


def _stop_time(a: float, v: float, b: float) -> float:
    """Time [s] for y' to reach 0 from v [m/s] under y'' = -a y' + b, where v b < 0.

    t* = log1p(-a v / b) / a = (-v/b) * log1p(x)/x with x = -a v/b >= 0 (stable as a -> 0).
    """
    x = -a * v / b
    ratio = 1.0 if x == 0.0 else math.log1p(x) / x
    return (-v / b) * ratio


class _Cart:
    """The cart between two samples, stepped with Python floats (numpy scalars are ~10x slower).

    m: moving mass [kg]; a = c/m [1/s]; f_k, f_s: kinetic and static friction [N]; h: Ts [s].
    """

    def __init__(self, m: float, c: float, f_k: float, f_s: float, h: float):
        self.m = m
        self.a = c / m
        self.f_k = f_k
        # Break away only when the drive also beats kinetic friction, else it would re-stick at
        # once (chatter); with f_s >= f_k, as Karnopp assumes, this is just f_s.
        self.f_break = max(f_s, f_k)
        self.h = h
        self.full = _phis(self.a, h)  # most phases span a whole sample: computed once
        self.advance = self._advance_linear if f_k == 0.0 and f_s == 0.0 else self._advance

    def _slip(self, y, v, b, t):
        e, p1, p2 = self.full if t == self.h else _phis(self.a, t)
        return y + p1 * v + p2 * b, e * v + p1 * b

    def _advance_linear(self, y: float, v: float, force: float):
        """No friction: one exact step of the linear cart under the constant force [N]."""
        return self._slip(y, v, force / self.m, self.h)

    def _advance(self, y: float, v: float, force: float):
        """One sample with stick-slip: (y, y') at t_k -> at t_k + h under drive ``force`` [N]."""
        left = self.h
        for _ in range(_MAX_EVENTS):
            if v == 0.0:
                if abs(force) <= self.f_break:
                    return y, 0.0  # stuck until the drive changes at the next sample
                s = 1.0 if force > 0.0 else -1.0
            else:
                s = 1.0 if v > 0.0 else -1.0
            b = (force - s * self.f_k) / self.m
            if s * b < 0.0:
                t_stop = _stop_time(self.a, v, b)
                if t_stop < left:
                    e, p1, p2 = _phis(self.a, t_stop)
                    y, v = y + p1 * v + p2 * b, 0.0
                    left -= t_stop
                    continue
            y, v_end = self._slip(y, v, b, left)
            # Analytically v keeps the sign s in this phase (or reaches 0 just at the end).
            return y, (v_end if v_end * s >= 0.0 else 0.0)
        raise RuntimeError(f"more than {_MAX_EVENTS} stick-slip events in one sample")


# ---------------------------------------------------------------- the plant's effects


def _as_floats(effect):
    """The effect with its parameters as Python floats (they may be JAX arrays)."""
    return dataclasses.replace(effect, **{n: float(getattr(effect, n)) for n in effect.param_names})


def _split_effects(plant: Plant):
    """(voltage effects in order, total kinetic friction [N], total static friction [N])."""
    voltage, f_k, f_s = [], 0.0, 0.0
    for effect in plant.effects:
        if isinstance(effect, EXACT_VOLTAGE_EFFECTS):
            voltage.append(_as_floats(effect))
        elif isinstance(effect, EXACT_FRICTION_EFFECTS):
            kinetic, static = effect.friction_levels()
            f_k, f_s = f_k + kinetic, f_s + static
        else:
            raise NotImplementedError(
                f"effect {type(effect).__name__} ({effect!r}): the exact simulator does not model "
                f"it yet (it models {', '.join(t.__name__ for t in _SUPPORTED)}); simulate it "
                "with the smooth simulator jaxcart.simulate, or add its exact form to "
                "jaxcart/exact.py"
            )
    return tuple(voltage), f_k, f_s


def _float_pid(controller: PID) -> PID:
    """The controller with Python-float gains (pid_update then runs on floats: fast)."""
    return dataclasses.replace(
        controller,
        **{n: float(getattr(controller, n)) for n in ("kp", "ki", "kd", "tau", "v_limit", "kb")},
    )


def _clip(v, limit):
    """Exact clip to [-limit, limit] on Python floats (same as hw.control_law.hard_clip)."""
    return min(max(v, -limit), limit)


# ---------------------------------------------------------------- the loop


def simulate_exact(plant: Plant, controller: PID | None, experiment: Experiment) -> Response:
    """Simulate one experiment exactly (hard clip, event-exact stick-slip); numpy float64 arrays.

    plant: :class:`jaxcart.Plant`; effects Saturation and Coulomb (others: NotImplementedError).
    controller: :class:`jaxcart.PID` for closed-loop experiments (ignored otherwise, may be None).
    experiment: :class:`jaxcart.Experiment` (tap, open_loop or closed_loop).

    Returns a :class:`jaxcart.Response` with the fields of :func:`jaxcart.simulate`: time t_k [s],
    position y_k and velocity y'_k [m, m/s] (state at t_k), reference r_k [m], error r_k - y_k
    [m], command u_k [V] (after the software limit), voltage [V] (after the amplifier effects),
    unlimited v_k [V] (the controller output before any limit),
    diverged (bool; from the first sample with |y| > DIVERGED_POSITION or not finite the
    simulation stops and the later samples are nan), kind.
    """
    ts = float(experiment.sample_time)
    kind = experiment.kind
    closed = kind == "closed_loop"
    if closed and controller is None:
        raise UserError("a closed-loop experiment needs a controller (a jaxcart.PID), got None")
    if closed and abs(controller.sample_time - ts) > 1e-12 * ts:
        raise UserError(
            f"controller sample_time {controller.sample_time} s differs from the experiment's "
            f"{ts} s; simulate them at one sample time"
        )
    voltage_effects, f_k, f_s = _split_effects(plant)
    m, c = float(plant.m), float(plant.c)
    gamma = float(plant.gamma) if plant.motor_connected else 0.0
    cart = _Cart(m, c, f_k, f_s, ts)

    signal = np.asarray(experiment.signal, dtype=np.float64)
    n = signal.shape[-1]
    y, v = float(experiment.y0), float(experiment.yd0)
    position = np.full(n, np.nan)
    velocity = np.full(n, np.nan)
    command = np.full(n, np.nan)
    voltage = np.full(n, np.nan)
    unlimited = np.full(n, np.nan)
    reference = signal.copy() if closed else np.full(n, y)
    signal_list = signal.tolist()

    if closed:
        pid = _float_pid(controller)
        state = PIDState(*(float(s) for s in pid_init(pid, signal_list[0], y, xp=np)))
    diverged = False
    for k in range(n):
        position[k], velocity[k] = y, v
        if not abs(y) <= DIVERGED_POSITION:  # also catches nan
            diverged = True
            break
        if closed:
            u, raw, state = pid_update(pid, state, signal_list[k], y, xp=np, clip=_clip)
        elif kind == "open_loop":
            u = raw = signal_list[k]
        else:
            u = raw = 0.0
        applied = u
        for effect in voltage_effects:
            applied = float(effect.exact(applied))
        command[k], voltage[k], unlimited[k] = u, applied, raw
        if k + 1 < n:
            y, v = cart.advance(y, v, gamma * applied)

    return Response(
        time=np.arange(n, dtype=np.float64) * ts,
        position=position,
        velocity=velocity,
        reference=reference,
        error=reference - position,
        command=command,
        voltage=voltage,
        diverged=diverged,
        unlimited=unlimited,
        kind=kind,
    )


def voltage_limit(plant: Plant, controller: PID) -> float:
    """The smaller of the controller's software limit and the plant's Saturation v_sat [V]."""
    limits = [float(e.v_sat) for e in plant.effects if isinstance(e, Saturation)]
    return min([float(controller.v_limit), *limits])


def step_info_exact(plant: Plant, controller: PID, experiment: Experiment) -> StepInfo:
    """:func:`jaxcart.metrics.step_info` of the exact run (saturation against
    :func:`voltage_limit`)."""
    response = simulate_exact(plant, controller, experiment)
    return step_info(response, v_limit=voltage_limit(plant, controller))
