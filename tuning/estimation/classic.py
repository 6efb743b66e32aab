"""The lab's classic analyses (the handout's hand methods), for comparison with
:mod:`tuning.estimation.fit`.

- :func:`loglinear_beq`, Part (i): while the tapped cart coasts with viscous friction only,
  v(t) = v0 e^{-(B_eq/m) t}; a least-squares line through ln|v| against t has slope -B_eq/m.
  Coulomb friction, which the method leaves out, bends the line down at low speed and makes
  B_eq come out too large.
- :func:`ramp_breakaway_fc`, Part (iii): under an open-loop voltage ramp (0.1 V/s) the cart
  stays put until gamma u exceeds the static friction; f_c = gamma u at the first sustained
  motion. The motion is seen some counts late, so the value is a little high.
- :func:`pcontrol_fc_bounds`: a P-controlled cart stuck at error e(inf) has |kp e(inf)| gamma
  <= f_c (else it would move): a lower bound. Every reversal or start of the cart from rest
  needed |gamma u| > f_c there: upper bounds.

Each returns a :class:`ClassicEstimate` with the value (or bounds) and a note of the method.

>>> import jaxcart as jc
>>> from jaxcart.synthetic import make_recording
>>> rec = make_recording(jc.tap_plant(B_eq=3.0), None, jc.tap(1.0, horizon=1.0), seed=0)
>>> round(loglinear_beq(rec).value, 2)
3.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from jaxcart.errors import UserError
from jaxcart.params import ENCODER_RESOLUTION
from tuning.estimation.engine.noise import encoder_count, noise_level
from tuning.estimation.engine.segments import coasting_segment, recording_name


@dataclass(frozen=True)
class ClassicEstimate:
    """Result of a classic analysis.

    name: the parameter ("B_eq" [kg/s] or "f_c" [N]); value: the estimate, or None where the
    method gives bounds only; stderr: the regression's standard error where there is one;
    lower, upper: bounds [same unit] or None; method: one line saying how; details: the
    intermediate numbers (times [s], voltages [V], ...).
    """

    name: str
    value: float | None
    method: str
    stderr: float | None = None
    lower: float | None = None
    upper: float | None = None
    details: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "value": self.value,
            "stderr": self.stderr,
            "lower": self.lower,
            "upper": self.upper,
            "method": self.method,
            "details": self.details,
        }


def _velocity(position, sample_time: float, window: float) -> np.ndarray:
    """Central differences of position [m/s], smoothed by a centred moving average of
    ``window`` [s] (edges padded with the end values)."""
    v = np.gradient(np.asarray(position, dtype=float), sample_time)
    w = max(1, int(round(window / sample_time)))
    if w == 1:
        return v
    padded = np.concatenate([np.full(w, v[0]), v, np.full(w, v[-1])])
    return np.convolve(padded, np.ones(w) / w, mode="same")[w:-w]


def _count(position, quantization) -> float:
    """The encoder count [m]: as given, else found in the data, else the IP02's."""
    if quantization is not None:
        return float(quantization)

    return encoder_count(position) or ENCODER_RESOLUTION


def _require(recording, kind: str, what: str):
    if recording.kind != kind:
        raise UserError(
            f"{recording_name(recording)}: {what} needs a {kind!r} recording, this one is "
            f"{recording.kind!r}"
        )


# ---------------------------------------------------------------- Part (i): log-linear B_eq


def loglinear_beq(
    recording,
    *,
    mass: float | None = None,
    segment: tuple[int, int] | None = None,
    min_fraction: float = 0.1,
    window: float = 0.01,
) -> ClassicEstimate:
    """B_eq [kg/s] from a tap by the handout's log-linear method.

    The velocity (central differences of position, ``window`` [s] moving average) is taken over
    the coasting part (``segment`` = sample indices (start, stop); default: found as
    :func:`tuning.estimation.engine.segments.coasting_segment` does) until it falls below
    ``min_fraction`` of its starting value (below that the encoder's counts dominate ln|v|). A
    least-squares line ln|v| = a + b t gives B_eq = -b m, with m = M + M_J of the recording's
    plant unless ``mass`` [kg] is given. ``stderr`` is the regression's (independent-error
    assumption).
    """
    _require(recording, "tap", "the log-linear B_eq method")
    y = np.asarray(recording.position, dtype=float)
    ts = float(recording.sample_time)
    t = np.asarray(recording.time, dtype=float)
    if segment is None:
        try:
            segment = coasting_segment(y, ts)
        except ValueError as exc:
            raise UserError(f"{recording_name(recording)}: {exc}") from None
    start, stop = segment
    v = _velocity(y, ts, window)[start:stop]
    speed = np.abs(v)
    keep = np.flatnonzero(speed < min_fraction * speed[0])
    end = int(keep[0]) if keep.size else speed.size
    if end < 10:
        raise UserError(
            f"{recording_name(recording)}: the coasting part has only {end} samples above "
            f"{min_fraction:.0%} of its starting speed; record a longer tap"
        )
    tt, lv = t[start : start + end], np.log(speed[:end])
    design = np.column_stack([np.ones(end), tt - tt[0]])
    coef, *_ = np.linalg.lstsq(design, lv, rcond=None)
    resid = lv - design @ coef
    cov = np.linalg.inv(design.T @ design) * float(resid @ resid) / max(end - 2, 1)
    m = float(recording.plant().m) if mass is None else float(mass)
    slope = float(coef[1])
    return ClassicEstimate(
        "B_eq",
        -slope * m,
        "log-linear (handout Part i): least-squares line through ln|v| vs t while coasting, "
        "B_eq = -slope * m",
        stderr=math.sqrt(cov[1, 1]) * m,
        details={
            "start_time": float(tt[0]),
            "stop_time": float(tt[-1]),
            "start_speed": float(speed[0]),
            "slope": slope,
            "mass": m,
        },
    )


# ---------------------------------------------------------------- Part (iii): ramp breakaway


def ramp_breakaway_fc(
    recording,
    *,
    gamma: float | None = None,
    counts: int = 3,
    hold: float = 0.05,
    quantization: float | None = None,
) -> ClassicEstimate:
    """f_c [N] from an open-loop voltage ramp: gamma times the voltage at breakaway.

    Breakaway is the first sample from which the cart stays at least ``counts`` encoder counts
    (``quantization`` [m] each; default: found in the data, else the IP02's) away from its
    starting position for ``hold`` [s] (first sustained motion). The voltage is the recorded
    command (column v) or the experiment's input; gamma [N/V] is the recording plant's unless
    given. The cart has moved a little before it is seen, so the value is slightly high (the
    details give the time and voltage).
    """
    _require(recording, "open_loop", "the ramp breakaway method")
    y = np.asarray(recording.position, dtype=float)
    quantization = _count(y, quantization)
    ts = float(recording.sample_time)
    u = recording.command
    if u is None:
        u = np.asarray(recording.experiment.signal, dtype=float)
    u = np.asarray(u, dtype=float)
    away = np.abs(y - y[0]) >= counts * quantization * (1 - 1e-6)
    hold_n = max(1, int(round(hold / ts)))
    # Sustained: the cart stays away for hold_n samples from k on.
    run = np.zeros(y.size + 1, dtype=int)
    for k in range(y.size - 1, -1, -1):
        run[k] = run[k + 1] + 1 if away[k] else 0
    moving = np.flatnonzero(run[:-1] >= min(hold_n, y.size))
    if moving.size == 0:
        raise UserError(
            f"{recording_name(recording)}: the cart never moves {counts} counts for {hold} s; "
            "ramp the voltage higher or record longer"
        )
    k = int(moving[0])
    g = float(recording.plant().gamma) if gamma is None else float(gamma)
    return ClassicEstimate(
        "f_c",
        g * abs(float(u[k])),
        f"ramp breakaway (handout Part iii): gamma * voltage at the first sustained motion "
        f"({counts} counts for {hold:g} s)",
        details={"time": float(recording.time[k]), "voltage": float(u[k]), "gamma": g},
    )


# ---------------------------------------------------------------- P control: f_c bounds


def pcontrol_fc_bounds(
    recording,
    *,
    gamma: float | None = None,
    rest: float = 0.1,
    hysteresis: int = 2,
    quantization: float | None = None,
) -> ClassicEstimate:
    """Bounds on f_c [N] from a P-controlled step (no integral action).

    Lower: the cart is stuck at the end with error e(inf) (mean of r - y over the last ``rest``
    [s], where it must not move more than one count), so gamma |u(inf)| <= f_c with
    u(inf) = clip(kp e(inf), v_limit) [V]. Upper: wherever the cart starts from rest or
    reverses (a turning point by more than ``hysteresis`` counts of ``quantization`` [m],
    default: found in the data) the drive beat static friction, f_c < gamma |u| there; the
    smallest such value is the bound. ``value`` is None.
    """
    _require(recording, "closed_loop", "the P-control f_c bounds")
    pid = recording.controller
    name = recording_name(recording)
    if pid is None or pid.ki != 0 or not pid.kp > 0:
        raise UserError(
            f"{name}: the f_c bounds need proportional control (kp > 0, ki = 0); "
            f"[controller] has {pid}"
        )
    y = np.asarray(recording.position, dtype=float)
    quantization = _count(y, quantization)
    r = np.asarray(recording.reference, dtype=float)
    ts = float(recording.sample_time)
    n_rest = max(2, int(round(rest / ts)))
    tail = y[-n_rest:]
    # Positions that are not whole counts scatter by their white noise: a cart at rest spans
    # up to about 8 of its standard deviations peak to peak (6 on average over 200 samples).
    still = max(quantization, 8 * noise_level(y)) if not encoder_count(y) else quantization
    if np.ptp(tail) > still * 1.01:
        raise UserError(
            f"{name}: the cart still moves in the last {rest:g} s "
            f"({np.ptp(tail) / quantization:.0f} counts); record until it is at rest"
        )
    e_inf = float(np.mean(r[-n_rest:] - tail))
    u_inf = float(np.clip(pid.kp * e_inf, -pid.v_limit, pid.v_limit))
    if recording.command is not None:
        u = np.asarray(recording.command, dtype=float)
    else:
        u = np.clip(pid.kp * (r - y), -pid.v_limit, pid.v_limit)
    g = float(recording.plant().gamma) if gamma is None else float(gamma)
    events = _breakaways(y, hysteresis * still)
    uppers = [
        (g * float(np.max(np.abs(u[max(k - 1, 0) : k + 2]))), float(recording.time[k]))
        for k in events
    ]
    upper, at = min(uppers) if uppers else (None, None)
    return ClassicEstimate(
        "f_c",
        None,
        "P-control steady state: gamma |kp e(inf)| <= f_c; f_c < gamma |u| where the cart "
        "started or reversed",
        lower=g * abs(u_inf),
        upper=upper,
        details={"e_inf": e_inf, "u_inf": u_inf, "gamma": g, "upper_time": at},
    )


def _breakaways(y, h: float) -> list[int]:
    """Sample indices where the cart leaves rest or reverses by more than ``h`` [m] (zigzag).

    The start counts as a breakaway at the last sample before the cart is first ``h`` away
    from its initial position; a reversal at the extreme sample before it comes back by
    ``h``."""
    events = []
    away = np.flatnonzero(np.abs(y - y[0]) > h)
    if away.size == 0:
        return events
    first = int(away[0])
    events.append(int(np.flatnonzero(y[:first] == y[0])[-1]))
    direction = 1.0 if y[first] > y[0] else -1.0
    ext, ext_k = y[first], first
    for k in range(first + 1, y.size):
        if direction * (y[k] - ext) > 0:
            ext, ext_k = y[k], k
        elif direction * (ext - y[k]) > h:
            events.append(ext_k)
            direction = -direction
            ext, ext_k = y[k], k
    return events
