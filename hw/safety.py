"""Safety checks of the hardware loop: every sample, before and after the control law.

    y_k --> [a number, not nan or inf] --> [encoder jump |y_k - y_k-1| <= jump_max]
        --> [track limit |y| <= x_max] --> [velocity |y_k - y_k-n| / (n Ts) <= speed_max]
        --> PID --> [clamp |u| <= v_max] --> u_k
    and the loop's watchdog: sample k read more than ``late_max`` after its deadline k Ts

Any check that fails raises :class:`Fault` with the reason as one line (what, the value, the
limit, when); the loop then writes 0 V in its ``finally``, leaves the board safe and records
the reason in the recording's [run] fault.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

#: The handout's track limit X_MAX [m]: the cart stops well inside the 0.814 m of travel.
X_MAX = 0.6


class Fault(Exception):
    """A safety check that stopped the run; ``str(fault)`` is the reason (one line).

    ``measured``: the faulting sample's position is a measurement (a track or velocity limit)
    and is recorded; False when it is not (nan, an encoder glitch): the recording then ends at
    the sample before, and the reason holds the value read.
    """

    def __init__(self, reason: str, *, measured: bool = True):
        super().__init__(reason)
        self.measured = measured


@dataclass(frozen=True)
class Limits:
    """Limits of a run (SI units).

    x_max: track limit |y| [m] (the handout's X_MAX = 0.6 m)
    v_max: voltage clamp |u| [V] (the amplifier's range)
    speed_max: velocity limit [m/s], on the position difference over ``speed_window`` samples
        (the cart's top speed at 6 V is gamma 6 / c = 0.8 m/s with the handout's values)
    jump_max: largest credible change of the encoder in one sample [m] (a jump is a glitch or a
        lost count, not motion: at speed_max it moves 1.5 um per ms)
    late_max: the loop's watchdog [s]: a sample read later than this after its deadline stops
        the run (0 or inf: off); not checked in virtual time
    speed_window: samples over which the velocity is estimated (beats encoder quantization)
    """

    x_max: float = X_MAX
    v_max: float = 6.0
    speed_max: float = 1.5
    jump_max: float = 0.005
    late_max: float = 0.005
    speed_window: int = 5

    def __post_init__(self):
        for name in ("x_max", "v_max", "speed_max", "jump_max"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise ValueError(f"{name} = {value!r}: give a positive number (SI units)")
        if not (isinstance(self.late_max, int | float) and self.late_max >= 0):
            raise ValueError(f"late_max = {self.late_max!r} s: give a number >= 0 (0: off)")
        if not (isinstance(self.speed_window, int) and self.speed_window >= 1):
            raise ValueError(f"speed_window = {self.speed_window!r}: give a whole number >= 1")

    def to_dict(self) -> dict:
        return asdict(self)


class Guard:
    """The per-sample checks of one run (state: the last positions)."""

    def __init__(self, limits: Limits, sample_time: float):
        self.limits = limits
        self.sample_time = float(sample_time)
        self._history: list[float] = []
        self._watch = limits.late_max > 0 and math.isfinite(limits.late_max)

    def check_position(self, k: int, y: float) -> None:
        """A number, encoder jump, track limit and velocity at sample k (position y [m]).

        The jump is checked before the track limit: a glitch to a far value is a glitch, not a
        cart beyond the track."""
        lim, t = self.limits, k * self.sample_time
        if not math.isfinite(y):
            raise Fault(
                f"encoder: read {y} instead of a position at sample {k} (t = {t:.3f} s); check "
                "the encoder cable and the board",
                measured=False,
            )
        history = self._history
        if history:
            jump = y - history[-1]
            if abs(jump) > lim.jump_max:
                raise Fault(
                    f"encoder jump: y changed by {jump:.4g} m in one sample (limit "
                    f"{lim.jump_max:g} m) at t = {t:.3f} s; check the encoder cable",
                    measured=False,
                )
        if not abs(y) <= lim.x_max:
            raise Fault(f"track limit: y = {y:.4g} m beyond +/-{lim.x_max:g} m at t = {t:.3f} s")
        history.append(y)
        n = lim.speed_window
        if len(history) > n:
            del history[0]
            speed = (y - history[0]) / (n * self.sample_time)
            if abs(speed) > lim.speed_max:
                raise Fault(
                    f"velocity limit: |y'| = {abs(speed):.3g} m/s > {lim.speed_max:g} m/s at "
                    f"t = {t:.3f} s"
                )

    def clamp(self, u: float) -> float:
        """The voltage clamped to [-v_max, v_max] [V] (nan -> fault)."""
        v_max = self.limits.v_max
        if u != u:
            raise Fault("voltage: the controller computed nan; check the gains")
        return min(max(u, -v_max), v_max)

    def check_late(self, k: int, lateness: float) -> None:
        """The loop's watchdog: sample k read ``lateness`` [s] after its deadline."""
        if self._watch and lateness > self.limits.late_max:
            raise Fault(
                f"watchdog: sample {k} (t = {k * self.sample_time:.3f} s) was read "
                f"{lateness * 1e3:.3g} ms late (limit {self.limits.late_max * 1e3:g} ms); the "
                f"machine is too busy for real time"
            )
