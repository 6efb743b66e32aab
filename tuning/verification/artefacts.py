"""What real recordings carry and jaxcart's model does not: the independent generator's artefacts,
each switchable, with the random draws of one run.

Defaults (:data:`REALISTIC`) are sized to what the lab's hardware shows or plausibly carries:
the IP02's encoder (2.275e-5 m a count) read by the controller, the start anywhere within a
count, the sampling instants of a 1 kHz loop on a desktop OS scattered by 10 us, an amplifier
whose offset and gain wander by a few millivolts and a few tenths of a percent over a run and
whose output lags by 0.1 ms (a motor's L/R: 0.18 mH / 2.6 ohm = 0.07 ms), a drive that gives a
little more or less from run to run (1 % gain, 3 % limit), and a hand's push of varying shape.
:data:`NONE` turns every one off (the exact position, sampled exactly on time).

>>> NONE.quantization, REALISTIC.quantization
(0.0, 2.275e-05)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from hw.handout import ENCODER_RESOLUTION

#: The push shapes of a tap (a hand's push, as a function of s = (t - start)/length in [0, 1]).
PUSH_SHAPES = ("rectangle", "half_sine", "triangle", "trapezoid")
#: A drawn push lasts between these [s].
PUSH_LENGTHS = (0.05, 0.15)
#: The push of a tap without the artefact: a rectangle of this length [s].
PLAIN_PUSH = 0.1
#: Per-run draws of the drive are clipped at this many standard deviations.
SPREAD_CLIP = 2.5


@dataclass(frozen=True)
class Artefacts:
    """The artefacts of a run; 0 or False turns one off.

    quantization: encoder count [m]; 0 records the exact position
    phase: the count boundaries fall anywhere relative to the start (U[0, q)), else at it
    reads_counts: the controller reads the encoder's counts, as the hardware does (else the
      exact position, in the encoder's frame)
    jitter: standard deviation of each sampling instant about k Ts [s] (clipped at 3 sigma and
      Ts/4); the file still says t = k Ts. The command takes effect at the instant it was made
    drift_offset: amplitude of a slow wander of the drive's offset [V]
    drift_gain: amplitude of a slow wander of the drive's gain [-]
    drift_period: period of both wanders [s]: each is A (sin(2 pi t / P + phi) - sin phi),
      zero at the start (the amplifier as trimmed) with a random phase phi
    lag: a small first-order lag of the amplifier [s], added to the truth's own ``lag``
    gain_spread: relative standard deviation of the drive gain (gamma_scale) from run to run
    limit_spread: relative standard deviation of the drive's limits (v_sat and i_max, one draw
      for both: a supply that sags) from run to run
    push_shape: a tap's push drawn from PUSH_SHAPES with a length in PUSH_LENGTHS, else a
      rectangle of PLAIN_PUSH s
    """

    quantization: float = ENCODER_RESOLUTION
    phase: bool = True
    reads_counts: bool = True
    jitter: float = 1e-5
    drift_offset: float = 0.005
    drift_gain: float = 0.003
    drift_period: float = 20.0
    lag: float = 1e-4
    gain_spread: float = 0.01
    limit_spread: float = 0.03
    push_shape: bool = True

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool):
                continue
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"Artefacts.{f.name} = {value!r}: give a number >= 0")
            if f.name.endswith("_spread") and not value < 1 / SPREAD_CLIP:
                raise ValueError(f"Artefacts.{f.name}: give a share below {1 / SPREAD_CLIP}")
        if not self.drift_period > 0:
            raise ValueError("Artefacts.drift_period must be positive")

    def replace(self, **changes) -> Artefacts:
        return replace(self, **changes)


REALISTIC = Artefacts()
NONE = Artefacts(
    quantization=0.0,
    phase=False,
    reads_counts=False,
    jitter=0.0,
    drift_offset=0.0,
    drift_gain=0.0,
    lag=0.0,
    gain_spread=0.0,
    limit_spread=0.0,
    push_shape=False,
)


class Draws(NamedTuple):
    """The random numbers of one run (every one drawn whatever is switched off, so that turning
    one artefact off leaves the others' draws as they were).

    phase: where the start lies within its count [m]; instants: the sampling instants [s];
    gain_factor, limit_factor: this run's drive gain and limits relative to the cart's [-];
    drift_phases: (gain, offset) [rad]; push: (shape, length [s]).
    """

    phase: float
    instants: np.ndarray
    gain_factor: float
    limit_factor: float
    drift_phases: tuple
    push: tuple


def draw(artefacts: Artefacts, seed, n: int, sample_time: float) -> Draws:
    """The draws of a run of ``n`` samples of ``sample_time`` [s] from ``seed``."""
    rng = np.random.default_rng(seed)
    a = artefacts
    u_phase = float(rng.uniform())
    z = rng.standard_normal(n)
    z_gain, z_limit = (float(np.clip(x, -SPREAD_CLIP, SPREAD_CLIP)) for x in rng.standard_normal(2))
    phases = tuple(float(x) for x in rng.uniform(0.0, 2 * math.pi, 2))
    shape = PUSH_SHAPES[int(rng.integers(len(PUSH_SHAPES)))]
    length = float(rng.uniform(*PUSH_LENGTHS))
    jitter = a.jitter * np.clip(z, -3.0, 3.0)
    jitter = np.clip(jitter, -sample_time / 4, sample_time / 4)
    jitter[0] = 0.0  # the run starts at t = 0
    return Draws(
        phase=u_phase * a.quantization if a.phase else 0.0,
        instants=np.arange(n) * sample_time + jitter,
        gain_factor=1.0 + a.gain_spread * z_gain,
        limit_factor=1.0 + a.limit_spread * z_limit,
        drift_phases=phases,
        push=(shape, length) if a.push_shape else ("rectangle", PLAIN_PUSH),
    )


def drift(artefacts: Artefacts, phases: tuple):
    """``f(t) -> (gain [-], offset [V])`` of the drive's slow wander, or None when off."""
    a_gain, a_off = artefacts.drift_gain, artefacts.drift_offset
    if a_gain == 0 and a_off == 0:
        return None
    omega = 2 * math.pi / artefacts.drift_period
    p_gain, p_off = phases
    s_gain, s_off = math.sin(p_gain), math.sin(p_off)

    def wander(t):
        return (
            1.0 + a_gain * (math.sin(omega * t + p_gain) - s_gain),
            a_off * (math.sin(omega * t + p_off) - s_off),
        )

    return wander


def push_profile(shape: str, s: float) -> float:
    """The push's force relative to its peak at s = (t - start) / length, 0 outside [0, 1]."""
    if not 0.0 <= s <= 1.0:
        return 0.0
    if shape == "rectangle":
        return 1.0
    if shape == "half_sine":
        return math.sin(math.pi * s)
    if shape == "triangle":
        return 1.0 - abs(2.0 * s - 1.0)
    if shape == "trapezoid":
        return min(1.0, 4.0 * s, 4.0 * (1.0 - s))
    raise ValueError(f"push shape {shape!r}: one of {', '.join(PUSH_SHAPES)}")
