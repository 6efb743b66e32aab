"""The independent generator's experiments: closed-loop references (step, ramp, a square wave that
moves both ways, any sequence), open-loop voltages (step, ramp, any sequence) and the tap (motor
unplugged: a hand's push, then a coast to rest). Each holds its sampled signal at t_k = k Ts.

>>> from jaxcart import PID
>>> e = square(PID(kp=40.0, kd=3.0), 0.2, period=1.0, horizon=2.0)
>>> float(e.signal[0]), float(e.signal[600]), e.signal.size
(0.2, 0.0, 2001)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("closed_loop", "open_loop", "tap")


@dataclass(frozen=True, eq=False)
class Experiment:
    """One experiment.

    kind: "closed_loop" | "open_loop" | "tap"; signal: the reference r_k [m] (closed loop) or
    the command u_k [V] (open loop) at t_k = k Ts, zeros for a tap; sample_time: Ts [s];
    pid: the controller of a closed loop (a :class:`jaxcart.PID`); label: what it is, in words;
    speed: a tap's speed at the end of the push [m/s]; rest: a tap's time at rest before the
    push [s].
    """

    kind: str
    signal: np.ndarray
    sample_time: float = 0.001
    pid: object = None
    label: str = ""
    speed: float = 0.0
    rest: float = 0.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind {self.kind!r}: one of {', '.join(KINDS)}")
        if (self.kind == "closed_loop") != (self.pid is not None):
            raise ValueError("a closed loop needs its pid, and only a closed loop has one")
        if self.pid is not None and abs(self.pid.sample_time - self.sample_time) > 1e-12:
            raise ValueError(
                f"the pid runs at {self.pid.sample_time} s, the experiment at {self.sample_time} s"
            )
        if self.kind == "tap" and not (self.speed != 0 and self.rest >= 0):
            raise ValueError("a tap needs a speed (> 0 towards +y, < 0 towards -y) and rest >= 0")
        signal = np.asarray(self.signal, dtype=np.float64)
        if signal.ndim != 1 or signal.size < 2 or not np.all(np.isfinite(signal)):
            raise ValueError("the signal must be a finite 1-D sequence of at least 2 samples")
        object.__setattr__(self, "signal", signal)

    @property
    def n(self) -> int:
        return self.signal.size

    @property
    def horizon(self) -> float:
        return (self.n - 1) * self.sample_time


def _times(horizon: float, sample_time: float) -> np.ndarray:
    if not (horizon > 0 and sample_time > 0):
        raise ValueError("horizon and sample_time must be positive")
    return np.arange(int(round(horizon / sample_time)) + 1) * sample_time


def step(pid, amplitude: float, *, horizon: float = 2.0) -> Experiment:
    """Closed loop, the reference stepped to ``amplitude`` [m] at t = 0."""
    t = _times(horizon, pid.sample_time)
    return Experiment(
        "closed_loop",
        np.full(t.size, float(amplitude)),
        pid.sample_time,
        pid,
        f"step {amplitude} m",
    )


def ramp(pid, slope: float, *, horizon: float = 2.0) -> Experiment:
    """Closed loop, the reference r = slope t [m/s]."""
    t = _times(horizon, pid.sample_time)
    return Experiment("closed_loop", slope * t, pid.sample_time, pid, f"ramp {slope} m/s")


def square(pid, amplitude: float, *, period: float, horizon: float, low: float = 0.0):
    """Closed loop, a square wave: ``amplitude`` [m] for the first half of each ``period`` [s],
    ``low`` [m] for the second (the cart moves out and back)."""
    t = _times(horizon, pid.sample_time)
    first_half = np.floor(2 * t / period + 1e-9) % 2 == 0
    r = np.where(first_half, float(amplitude), float(low))
    label = f"square wave {low}/{amplitude} m, period {period} s"
    return Experiment("closed_loop", r, pid.sample_time, pid, label)


def reference_sequence(pid, r) -> Experiment:
    """Closed loop with any sampled reference r_k [m]."""
    return Experiment("closed_loop", np.asarray(r, float), pid.sample_time, pid, "reference")


def voltage_step(amplitude: float, *, horizon: float = 2.0, sample_time: float = 0.001):
    """Open loop, the command stepped to ``amplitude`` [V] at t = 0."""
    t = _times(horizon, sample_time)
    return Experiment(
        "open_loop", np.full(t.size, float(amplitude)), sample_time, label=f"step {amplitude} V"
    )


def voltage_ramp(slope: float, *, horizon: float = 5.0, sample_time: float = 0.001):
    """Open loop, the command u = slope t [V/s]."""
    t = _times(horizon, sample_time)
    return Experiment("open_loop", slope * t, sample_time, label=f"voltage ramp {slope} V/s")


def voltage_sequence(u, *, sample_time: float = 0.001) -> Experiment:
    """Open loop with any sampled command u_k [V]."""
    return Experiment("open_loop", np.asarray(u, float), sample_time, label="voltage sequence")


def tap(*, speed: float = 0.6, rest: float = 0.3, horizon: float = 1.5, sample_time=0.001):
    """The tap test: the motor unplugged, the cart at rest for ``rest`` [s], pushed by hand to
    about ``speed`` [m/s] (< 0: towards -y; the push's shape and length are the artefacts'),
    then coasting."""
    t = _times(horizon, sample_time)
    label = f"tap: rest {rest} s, pushed to {speed} m/s, coasting"
    return Experiment("tap", np.zeros(t.size), sample_time, label=label, speed=speed, rest=rest)
