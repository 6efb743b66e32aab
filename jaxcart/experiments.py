"""Experiments: what is done to the cart (tap, open-loop voltage, closed-loop reference).

An experiment is a pytree of sampled signals at the controller's sample time: the reference
r_k [m] (closed loop) or the voltage command u_k [V] (open loop), and the initial state.
Samples are at t_k = k * sample_time, k = 0 .. n_samples - 1.

>>> exp = step(0.5, horizon=3.0)
>>> exp.n_samples, float(exp.reference[-1])
(3001, 0.5)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart.parallel import put

KINDS = ("tap", "open_loop", "closed_loop")


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Experiment:
    """One experiment on the cart.

    signal: r_k [m] for "closed_loop", the voltage command u_k [V] for "open_loop",
        zeros for "tap"; shape (n_samples,)
    y0: initial position [m]
    yd0: initial velocity [m/s] (the tap's push)
    kind: "tap" | "open_loop" | "closed_loop" (static)
    sample_time: Ts [s] (static)
    """

    signal: jax.Array
    y0: float = 0.0
    yd0: float = 0.0
    kind: str = field(default="closed_loop", metadata={"static": True})
    sample_time: float = field(default=0.001, metadata={"static": True})

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"experiment kind {self.kind!r}: use one of {', '.join(KINDS)}")

    @property
    def n_samples(self) -> int:
        return int(np.shape(self.signal)[-1])

    @property
    def time(self):
        """Sample times t_k [s]."""
        return jnp.arange(self.n_samples) * self.sample_time

    @property
    def reference(self):
        """Reference r_k [m] (closed loop); for the other kinds, the initial position."""
        if self.kind == "closed_loop":
            return self.signal
        return jnp.zeros_like(self.signal) + self.y0


def _n_samples(horizon: float, sample_time: float) -> int:
    if not horizon > 0:
        raise ValueError(f"horizon = {horizon!r} s: it must be positive")
    if not sample_time > 0:
        raise ValueError(f"sample_time = {sample_time!r} s: it must be positive")
    return int(round(horizon / sample_time)) + 1


def _times(horizon, sample_time):
    return np.arange(_n_samples(horizon, sample_time)) * sample_time


def step(amplitude: float, *, horizon: float = 3.0, sample_time: float = 0.001, y0=0.0):
    """Closed-loop step of the reference to ``amplitude`` [m] at t = 0."""
    t = _times(horizon, sample_time)
    return Experiment(put(np.full(t.shape, amplitude), float), y0=y0, sample_time=sample_time)


def ramp(slope: float, *, horizon: float = 3.0, sample_time: float = 0.001, y0=0.0):
    """Closed-loop ramp reference r = y0 + slope * t [m, m/s]."""
    t = _times(horizon, sample_time)
    return Experiment(put(y0 + slope * t, float), y0=y0, sample_time=sample_time)


def setpoints(times, values, *, horizon: float, sample_time: float = 0.001, y0=0.0):
    """Closed-loop piecewise-constant reference: ``values[i]`` [m] from ``times[i]`` [s] on
    (before ``times[0]`` the reference is ``y0``). The slider moves of Part (v)."""
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    if times.shape != values.shape or np.any(np.diff(times) <= 0):
        raise ValueError("setpoints: times must increase and match values one to one")
    t = _times(horizon, sample_time)
    index = np.searchsorted(times, t + 1e-9 * sample_time, side="right") - 1
    r = np.where(index >= 0, values[np.maximum(index, 0)], y0)
    return Experiment(put(r, float), y0=y0, sample_time=sample_time)


def reference_sequence(r, *, sample_time: float = 0.001, y0=0.0):
    """Closed loop with any sampled reference r_k [m]."""
    return Experiment(put(r, float), y0=y0, sample_time=sample_time)


def tap(velocity: float, *, horizon: float = 2.0, sample_time: float = 0.001, y0=0.0):
    """Tap test: the cart starts at ``y0`` [m] with ``velocity`` [m/s], motor unplugged."""
    t = _times(horizon, sample_time)
    return Experiment(
        put(np.zeros(t.shape), float), y0=y0, yd0=velocity, kind="tap", sample_time=sample_time
    )


def voltage_sequence(u, *, sample_time: float = 0.001, y0=0.0, yd0=0.0):
    """Open loop with any sampled voltage command u_k [V]."""
    return Experiment(put(u, float), y0=y0, yd0=yd0, kind="open_loop", sample_time=sample_time)


def voltage_step(amplitude: float, *, horizon: float = 2.0, sample_time: float = 0.001):
    """Open-loop voltage step to ``amplitude`` [V] at t = 0."""
    return voltage_sequence(
        np.full(_times(horizon, sample_time).shape, float(amplitude)), sample_time=sample_time
    )


def voltage_ramp(slope: float, *, horizon: float = 20.0, sample_time: float = 0.001):
    """Open-loop voltage ramp u = slope * t [V/s] (Part (iii) uses 0.1 V/s)."""
    return voltage_sequence(slope * _times(horizon, sample_time), sample_time=sample_time)
