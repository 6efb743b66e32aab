"""The Coulomb dead band of a P loop, stated so that it holds for a finite recording read through
an encoder (Part (iii) of the report).

The cart m y'' + c y' = gamma u - f_c sign(y') under P control u = k e, e = r - y, can rest only
where the drive does not beat friction, k gamma |e| <= f_c: the dead band |e| <= b,

    b = f_c / (k gamma)   [m].

How it gets there depends on the poles of the linear loop m s^2 + c s + k gamma (valid while
the cart moves one way with kinetic friction f_c: the error's distance x = e - b from the
band's edge obeys m x'' + c x' + k gamma x = 0):

- complex poles: the cart overshoots, stops at a reversal and sticks there once inside the
  band; at rest |e| <= b exactly.
- real poles (overdamped): starting at rest with x(0) = x0 = |e(0)| - b > 0 it creeps towards
  the edge, x(t) = x0 (s2 e^(s1 t) - s1 e^(s2 t)) / (s2 - s1) with s1 the slower pole, and never
  stops in finite time: at the end of a recording of length T the error is still x(T) beyond
  the edge (:func:`creep`), and the friction force is then slightly exceeded.

The encoder reads whole counts q below the cart (y_measured = q floor(y / q)), so a recorded
error can exceed the true one by up to one count. Together, a P-control recording that ends at
T has

    |e_measured(T)| <= b + x(T) + q,

which is what the report states and checks (tested against the exact simulator in
tests/test_lab_deadband.py). The same count bounds f_c from below: a cart at rest with recorded
error e has f_c >= k gamma (|e| - q).

>>> round(band(0.45, 10.0, 1.7235) * 1e3, 4)   # [mm]
26.1097
"""

from __future__ import annotations

import math

import numpy as np


def band(f_c: float, k: float, gamma: float) -> float:
    """Half-width b = f_c / (k gamma) [m] of the dead band (f_c [N], k [V/m], gamma [N/V])."""
    return float(f_c) / (float(k) * float(gamma))


def poles(m: float, c: float, gamma: float, k: float) -> np.ndarray:
    """Roots [1/s] of m s^2 + c s + k gamma, the P loop while the cart slides one way."""
    return np.roots([float(m), float(c), float(k) * float(gamma)])


def overdamped(m: float, c: float, gamma: float, k: float) -> bool:
    """Both poles real: the cart creeps to the band's edge without overshoot."""
    return float(c) ** 2 >= 4.0 * float(m) * float(k) * float(gamma)


def creep(m, c, gamma, k, f_c, step, t) -> float:
    """How far beyond the band's edge [m] the error still is at time t [s] of a P loop started
    at rest with error ``step`` [m] (linear model, no voltage limit): x(t) above, 0 when the
    poles are complex (the cart stops at a reversal) or the start is inside the band."""
    x0 = abs(float(step)) - band(f_c, k, gamma)
    if x0 <= 0 or not overdamped(m, c, gamma, k):
        return 0.0
    s1, s2 = sorted(poles(m, c, gamma, k).real, reverse=True)  # s1: the slower (closer to 0)
    if math.isclose(s1, s2, rel_tol=1e-9):  # critically damped: x0 (1 - s t) e^(s t)
        return x0 * (1.0 - s1 * t) * math.exp(s1 * t)
    return x0 * (s2 * math.exp(s1 * t) - s1 * math.exp(s2 * t)) / (s2 - s1)


def f_c_lower(e_inf: float, k: float, gamma: float, q: float, v_limit: float = math.inf):
    """Lower bound on f_c [N] from a P-controlled cart at rest with recorded error e_inf [m]:
    gamma min(k (|e_inf| - q), v_limit), one count q [m] taken off for the encoder."""
    return float(gamma) * min(float(k) * max(abs(float(e_inf)) - float(q), 0.0), v_limit)
