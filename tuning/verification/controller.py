"""The lab's discrete PID, written again from docs/design.md "The control law" (not imported from
``hw/control_law.py``, whose stepping jaxcart's simulators run), so that the independent
generator's loop checks that code too. Sample time Ts [s]:

    e_k = r_k - y_k
    s_k = e_k (derivative on error) or -y_k (on measurement);  s_-1 = s_0
    d_k = (tau d_{k-1} + s_k - s_{k-1}) / (tau + Ts)
    v_k = kp e_k + ki I_k + kd d_k,   I_{k+1} = I_k + Ts e_k   (forward Euler)
    u_k = clip(v_k, -v_limit, v_limit)

Anti-windup "clamping" keeps I_{k+1} = I_k while v_k is beyond the limit and e_k drives it
further; "back_calculation" integrates e_k + kb (u_k - v_k) / ki. The settings come as a
:class:`jaxcart.PID` (``hw.control_law.PID``: kp [V/m], ki [V/(m s)], kd [V s/m], tau [s],
v_limit [V], kb [1/s], sample_time [s], derivative_on, anti_windup), used as a record only.

>>> from jaxcart import PID
>>> law = DiscretePID(PID(kp=10.0, ki=1.0))
>>> law.start(0.1, 0.0)
>>> law.update(0.1, 0.0)  # (u_0, v_0): kp e_0, the integral still 0
(1.0, 1.0)
"""

from __future__ import annotations

import math


class DiscretePID:
    """One controller's memory and its sample update."""

    def __init__(self, pid):
        self.kp, self.ki, self.kd = float(pid.kp), float(pid.ki), float(pid.kd)
        self.tau, self.ts = float(pid.tau), float(pid.sample_time)
        self.limit = float(pid.v_limit)
        self.kb = float(pid.kb)
        self.on_error = pid.derivative_on == "error"
        self.mode = pid.anti_windup
        if self.mode not in ("none", "clamping", "back_calculation"):
            raise ValueError(f"anti_windup {self.mode!r}: none, clamping or back_calculation")
        if self.mode != "none" and math.isinf(self.limit):
            raise ValueError("anti-windup needs a finite v_limit")
        self.integral = self.derivative = self.previous = 0.0

    def _s(self, r, y):
        return r - y if self.on_error else -y

    def start(self, r0: float, y0: float) -> None:
        """Before the first sample: I_0 = 0, d_-1 = 0, s_-1 = s_0."""
        self.integral, self.derivative = 0.0, 0.0
        self.previous = self._s(r0, y0)

    def update(self, r: float, y: float) -> tuple[float, float]:
        """(u_k, v_k) [V] for reference r_k and measurement y_k [m]; advances the memory."""
        e = r - y
        s = self._s(r, y)
        self.derivative = (self.tau * self.derivative + s - self.previous) / (self.tau + self.ts)
        self.previous = s
        v = self.kp * e + self.ki * self.integral + self.kd * self.derivative
        u = v if abs(v) <= self.limit else math.copysign(self.limit, v)
        if self.mode == "clamping" and u != v and e * v > 0:
            pass  # held: the output is limited and the error pushes further
        elif self.mode == "back_calculation" and self.ki != 0:
            self.integral += self.ts * (e + self.kb * (u - v) / self.ki)
        else:
            self.integral += self.ts * e
        return u, v
