"""The canonical discrete PID of the lab, written once for numpy and for JAX.

Both the simulator (JAX) and the hardware loop (numpy) call these functions, so the controller
that is tuned is exactly the controller that runs. The code uses only arithmetic and the array
namespace passed as ``xp`` (``numpy`` or ``jax.numpy``); it never imports jax itself.

    r_k --(+)-- e_k --> [ kp + ki*Ts/(z-1) + kd*(z-1)/((tau+Ts)z - tau) ] -- v_k --> [clip] -- u_k
          |-                                                                          (held, ZOH)
    y_k --'

Equations (sample time Ts, docs/design.md, "The control law"):
    e_k = r_k - y_k
    s_k = e_k (derivative on error) or -y_k (on measurement); s_-1 = s_0
    d_k = (tau d_{k-1} + s_k - s_{k-1}) / (tau + Ts)
    v_k = kp e_k + ki I_k + kd d_k,     I_{k+1} = I_k + Ts e_k  (forward Euler)
    u_k = clip(v_k, -v_limit, v_limit)
Anti-windup: "clamping" holds I while u is at the limit and e pushes further; "back_calculation"
adds kb (u_k - v_k) / ki to the integrator input (Simulink's form, kb in 1/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

DERIVATIVE_MODES = ("error", "measurement")
ANTI_WINDUP_MODES = ("none", "clamping", "back_calculation")


@dataclass(frozen=True)
class PID:
    """Settings of the canonical discrete PID. Units: position in m, voltage in V, time in s.

    kp: proportional gain [V/m]
    ki: integral gain [V/(m s)]
    kd: derivative gain [V s/m]
    tau: derivative filter time constant [s] (Simulink N = 1/tau); 0 gives a pure difference
    v_limit: software voltage limit [V]; ``math.inf`` for none
    kb: back-calculation gain [1/s] (used with anti_windup="back_calculation")
    sample_time: controller period Ts [s] (static: changing it changes the loop)
    derivative_on: "error" (the lab's Simulink PID block) or "measurement" (static)
    anti_windup: "none", "clamping" or "back_calculation" (static)
    """

    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    tau: float = 0.01
    v_limit: float = math.inf
    kb: float = 1.0
    sample_time: float = 0.001
    derivative_on: str = "error"
    anti_windup: str = "none"

    def __post_init__(self):
        if self.derivative_on not in DERIVATIVE_MODES:
            raise ValueError(
                f"derivative_on = {self.derivative_on!r}: use one of {', '.join(DERIVATIVE_MODES)}"
            )
        if self.anti_windup not in ANTI_WINDUP_MODES:
            raise ValueError(
                f"anti_windup = {self.anti_windup!r}: use one of {', '.join(ANTI_WINDUP_MODES)}"
            )
        for name in (*PID_DATA_FIELDS, "sample_time"):
            value = getattr(self, name)
            if name == "sample_time" or _is_number(value):  # a JAX array is the tuner's
                problem = setting_problem(name, value, allow_negative_gains=True)
                if problem:
                    raise ValueError(f"{name} = {problem}")
        if (
            self.anti_windup != "none"
            and isinstance(self.v_limit, float | int)
            and math.isinf(self.v_limit)
        ):
            raise ValueError(
                f"anti_windup = {self.anti_windup!r} acts on the software limit, but v_limit is "
                "infinite; give v_limit (e.g. 6 V, the amplifier's range) or anti_windup='none'"
            )

    def to_dict(self) -> dict:
        """Every setting as plain Python numbers and strings (the gains-file form)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


#: Field names that are numbers (array leaves in JAX); the rest are static configuration.
PID_DATA_FIELDS = ("kp", "ki", "kd", "tau", "v_limit", "kb")
PID_META_FIELDS = ("sample_time", "derivative_on", "anti_windup")
#: Each setting's default (what a file or a command line that omits it gets).
DEFAULTS = {f.name: f.default for f in fields(PID)}


#: Each number's unit (the gains file writes them beside the settings).
UNITS = {
    "kp": "V/m",
    "ki": "V/(m s)",
    "kd": "V s/m",
    "tau": "s",
    "v_limit": "V",
    "kb": "1/s",
    "sample_time": "s",
}
GAINS = ("kp", "ki", "kd")
#: The rule of each number other than a gain: (the rule, the fix). A gain is any finite number
#: >= 0 (see :func:`setting_problem`); every setting is finite except v_limit, whose inf is
#: "no software limit".
_RULES = {
    "tau": ("it must be >= 0", "0 is a pure difference, the lab's 0.01 s a filtered one"),
    "kb": ("it must be >= 0", "the back-calculation gain, e.g. 1"),
    "v_limit": ("it must be positive", "give the limit, e.g. 6 (the amplifier), or inf for none"),
    "sample_time": ("it must be positive", "the lab's controller runs at 0.001 s"),
}


def setting_problem(name: str, value, *, allow_negative_gains: bool = False) -> str | None:
    """What is wrong with ``value`` as the PID setting ``name`` (one of :data:`UNITS`), as one
    line "VALUE UNIT: the rule; the fix" for the caller to put after its own field name, or
    None when it is fine. The one validation of a PID's numbers: PID(...), the experiment
    file's [controller], the gains file and the command line all call it.

    The rule of the gains kp, ki, kd: the lab's gains are >= 0, since v = kp e + ki I + kd d
    with e = r - y, so a negative gain pushes the cart away from the reference (positive
    feedback): a sign error. Settings chosen for the cart (a gains file, ``tune``'s --start) are
    refused one. ``allow_negative_gains`` is for what records or represents a run: :class:`PID`
    itself and the experiment file's [controller], so that a sign error can be simulated and
    flagged as unstable before a run (jaxcart.plausibility, hw's pre-run check; issue 11), a run
    ``simulate`` wrote can be read back, and a controller identified from a recording may come
    out with a small negative gain. Every other rule is the same at every entry point.
    """
    unit = UNITS[name]
    if isinstance(value, bool) or not _is_number(value):
        hint = " (inf for no limit)" if name == "v_limit" else ""
        return f"{value!r}: give a number in {unit}{hint}"
    value = float(value)
    shown = f"{value!r} {unit}"
    if math.isnan(value) or (math.isinf(value) and not (name == "v_limit" and value > 0)):
        return f"{shown}: give a finite number" + (" (inf for no limit)" * (name == "v_limit"))
    if name in GAINS:
        if value < 0 and not allow_negative_gains:
            return (
                f"{shown}: a negative gain is positive feedback (a sign error: the error is "
                f"e = r - y); the lab's gains are >= 0, so drop the minus sign"
            )
        return None
    rule, fix = _RULES[name]
    ok = value > 0 if "positive" in rule else value >= 0
    return None if ok else f"{shown}: {rule}; {fix}"


def _is_number(value) -> bool:
    # Python and numpy numbers (np.float64 is a float; np.float32 and ints are np.number).
    return isinstance(value, int | float | np.number)


def float_pid(pid: PID) -> PID:
    """The controller with Python-float numbers (the control law then runs on floats: fast in
    the exact simulator and the hardware loop)."""
    return replace(pid, **{n: float(getattr(pid, n)) for n in PID_DATA_FIELDS})


def _plain(value):
    if isinstance(value, str):
        return value
    value = float(value)
    return value


class PIDState(NamedTuple):
    """Controller memory between samples.

    integral: I_k [m s]; derivative: d_k, the filtered derivative of s [m/s];
    previous: s_{k-1} [m].
    """

    integral: object
    derivative: object
    previous: object


def _signal(pid: PID, r, y):
    return (r - y) if pid.derivative_on == "error" else -y


def pid_init(pid: PID, r0, y0, xp=np) -> PIDState:
    """Controller state before the first sample (I = 0, d = 0, s_-1 = s_0)."""
    s0 = _signal(pid, r0, y0)
    zero = xp.zeros_like(s0 * pid.kp)
    return PIDState(integral=zero, derivative=zero, previous=s0 + zero)


def hard_clip(v, limit, xp=np):
    """Exact saturation to [-limit, limit] (limit may be inf)."""
    return xp.clip(v, -limit, limit)


class Floats:
    """The array namespace of the control law on Python floats (numpy scalars are ~10x
    slower): the same arithmetic, so the same numbers. The hardware loop and the exact
    simulator pass it as ``xp`` with :func:`float_clip`."""

    abs = staticmethod(abs)

    @staticmethod
    def where(condition, a, b):
        return a if condition else b


def float_clip(v, limit):
    """:func:`hard_clip` on Python floats."""
    return min(max(v, -limit), limit)


def pid_update(pid: PID, state: PIDState, r, y, xp=np, clip=None):
    """One controller sample: returns (u_k, v_k, next state).

    ``v_k`` is the unlimited command and ``u_k`` the command after the software limit.
    ``clip(v, limit)`` defaults to the exact clip; the smooth simulator passes a smooth one.
    """
    return pid_stepper(pid, xp, clip)(state, r, y)


def pid_stepper(pid: PID, xp=np, clip=None):
    """``step(state, r, y) -> (u_k, v_k, next state)``: :func:`pid_update` with the
    controller's constants bound once, the same arithmetic (bit for bit). A loop that runs
    many samples (the exact simulator, the hardware loop) calls this once, then ``step``."""
    if clip is None:

        def clip(v, limit):
            return hard_clip(v, limit, xp)

    ts, kp, ki, kd, tau, limit = (pid.sample_time, pid.kp, pid.ki, pid.kd, pid.tau, pid.v_limit)
    on_error, mode = pid.derivative_on == "error", pid.anti_windup
    filt = 1.0 / (tau + ts)
    if mode == "back_calculation":
        safe_ki = xp.where(ki == 0, 1.0, ki)
        no_ki = ki == 0

    def step(state: PIDState, r, y):
        e = r - y
        s = (r - y) if on_error else -y  # _signal, inlined: this runs every sample
        d = (tau * state.derivative + s - state.previous) * filt
        v = kp * e + ki * state.integral + kd * d
        u = clip(v, limit)
        if mode == "clamping":
            # Hold I while the output is limited and the error drives it further into the limit.
            pushing = (xp.abs(v) > limit) & (e * v > 0)
            integral = xp.where(pushing, state.integral, state.integral + ts * e)
        elif mode == "back_calculation":
            correction = xp.where(no_ki, 0.0, pid.kb * (u - v) / safe_ki)
            integral = state.integral + ts * (e + correction)
        else:
            integral = state.integral + ts * e
        return u, v, PIDState(integral=integral, derivative=d, previous=s)

    return step
