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
        if not (isinstance(self.sample_time, float | int) and self.sample_time > 0):
            raise ValueError(f"sample_time = {self.sample_time!r} s: it must be a positive number")
        if (
            self.anti_windup != "none"
            and isinstance(self.v_limit, float | int)
            and math.isinf(self.v_limit)
        ):
            raise ValueError(
                f"anti_windup = {self.anti_windup!r} acts on the software limit, but v_limit is "
                "infinite; give v_limit (e.g. 6 V, the amplifier's range) or anti_windup='none'"
            )
        for name in ("tau", "v_limit", "kb"):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value >= 0:
                raise ValueError(f"{name} = {value!r}: it must be >= 0")

    def to_dict(self) -> dict:
        """Every setting as plain Python numbers and strings (the gains-file form)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


#: Field names that are numbers (array leaves in JAX); the rest are static configuration.
PID_DATA_FIELDS = ("kp", "ki", "kd", "tau", "v_limit", "kb")
PID_META_FIELDS = ("sample_time", "derivative_on", "anti_windup")


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


def pid_update(pid: PID, state: PIDState, r, y, xp=np, clip=None):
    """One controller sample: returns (u_k, v_k, next state).

    ``v_k`` is the unlimited command and ``u_k`` the command after the software limit.
    ``clip(v, limit)`` defaults to the exact clip; the smooth simulator passes a smooth one.
    """
    if clip is None:

        def clip(v, limit):
            return hard_clip(v, limit, xp)

    ts = pid.sample_time
    e = r - y
    s = _signal(pid, r, y)
    d = (pid.tau * state.derivative + s - state.previous) * (1.0 / (pid.tau + ts))
    v = pid.kp * e + pid.ki * state.integral + pid.kd * d
    u = clip(v, pid.v_limit)
    if pid.anti_windup == "clamping":
        # Hold I while the output is limited and the error drives it further into the limit.
        pushing = (xp.abs(v) > pid.v_limit) & (e * v > 0)
        integral = xp.where(pushing, state.integral, state.integral + ts * e)
    elif pid.anti_windup == "back_calculation":
        safe_ki = xp.where(pid.ki == 0, 1.0, pid.ki)
        correction = xp.where(pid.ki == 0, 0.0, pid.kb * (u - v) / safe_ki)
        integral = state.integral + ts * (e + correction)
    else:
        integral = state.integral + ts * e
    return u, v, PIDState(integral=integral, derivative=d, previous=s)
