"""The exact (verification) simulator: hard clip and event-exact Karnopp stick-slip, no smoothing.

Written independently of :mod:`jaxcart.smooth_sim` (no shared integration code) so that it can check
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
exact too). A kinetic level that differs by direction (f_k+ sliding right, f_k- left) keeps this:
within a slip phase the direction, hence the level, is fixed. Stick-slip events are found in
closed form (Karnopp, static level f_s >= kinetic f_k):

    start of sample, or velocity just reached 0 at time t* (closed form):
                      |
              y' == 0 ?  --no-->  slip, s = sgn(y'):  b = (F - s f_k)/m
                 | yes                |
                 v                    |  does y' reach 0 before the sample ends?
  -f_s- <= F <= f_s+ ?              |    (only if s b < 0; t* = log1p(-a y'/b)/a)
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

import bisect
import dataclasses
import itertools
import math
from typing import NamedTuple

import numpy as np

from hw.control_law import PID, Floats, PIDState, float_clip, float_pid, pid_init, pid_stepper
from jaxcart.effects import Held
from jaxcart.experiments import Experiment
from jaxcart.metrics import StepInfo, step_info
from jaxcart.params import Plant, voltage_limit
from jaxcart.runcheck import check_run
from jaxcart.smooth_sim import DIVERGED_POSITION, Response
from jaxcart.substeps import substeps_per_sample

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


class _Friction:
    """The plant's dry friction, its members combined (docs/design.md, "Effects"): kinetic
    levels K+(y) sliding right and K-(y) sliding left [N] (each the members' sum, held at 0 or
    above), the static level S [N] (stiction; None without) and the Stribeck speed v_s [m/s]
    (0: Karnopp's jump from S to the kinetic level). Sliding in direction s at speed q its
    magnitude is K_s + max(S - K_s, 0) exp(-(q / v_s)^2); a cart at rest breaks away in
    direction s only where s F > max(S, K_s) for the applied force F [N].

    ``constant``: (K+, K-) where no level varies within a slip phase (neither with the
    position nor with the speed), else None; ``varying``: the opposite.
    """

    def __init__(self, dry):
        self.dry = dry
        # Each member's levels as a function of y on plain floats, bound once per run.
        self._members = [e.exact_kinetic_sides() for e in dry]
        statics = [float(e.static()) for e in dry if e.static() is not None]
        self.static = max(statics) if statics else None
        speeds = [float(e.stribeck()) for e in dry if e.stribeck() is not None]
        self.v_s = max(speeds, default=0.0) if self.static is not None else 0.0
        positional = any(e.position_dependent for e in dry)
        self.varying = positional or self.v_s > 0.0
        self.constant = None if positional else self._sum(0.0)

    def _sum(self, y):
        right = left = 0.0
        for sides in self._members:
            r, lf = sides(y)
            right, left = right + float(r), left + float(lf)
        return max(right, 0.0), max(left, 0.0)

    def sides(self, y):
        """(K+, K-) [N] at position y [m]."""
        return self._sum(y) if self.constant is None else self.constant

    def level(self, y, s, speed):
        """The friction's magnitude [N] sliding in direction s at speed [m/s], position y [m]."""
        right, left = self.sides(y)
        k = right if s > 0.0 else left
        if self.v_s > 0.0 and self.static > k:
            k += (self.static - k) * math.exp(-((speed / self.v_s) ** 2))
        return k

    def breakaway(self, y, s):
        """The applied force [N] a cart at rest at y [m] must exceed in direction s to move."""
        right, left = self.sides(y)
        k = right if s > 0.0 else left
        return k if self.static is None else max(self.static, k)

    def stuck(self, y, applied):
        """True where a cart at rest at y [m] stays at rest under the applied force [N]."""
        return -self.breakaway(y, -1.0) <= applied <= self.breakaway(y, 1.0)


class _Cart:
    """The cart between two samples, stepped with Python floats (numpy scalars are ~10x slower).

    m: moving mass [kg]; a = c/m [1/s]; friction: the plant's :class:`_Friction` (constant
    levels); h: Ts [s].
    """

    def __init__(self, m: float, c: float, friction: _Friction, h: float):
        self.m = m
        self.a = c / m
        # Kinetic level sliding right and left, and the force that breaks the cart away each
        # way [N] (the drive must also beat kinetic friction, else it re-sticks at once).
        self.f_right, self.f_left = friction.constant
        self.break_right = friction.breakaway(0.0, 1.0)
        self.break_left = friction.breakaway(0.0, -1.0)
        self.h = h
        self.full = _phis(self.a, h)  # most phases span a whole sample: computed once
        idle = self.break_right == 0.0 and self.break_left == 0.0
        self.advance = self._advance_linear if idle else self._advance

    def _slip(self, y, v, b, t):
        e, p1, p2 = self.full if t == self.h else _phis(self.a, t)
        return y + p1 * v + p2 * b, e * v + p1 * b

    def _advance_linear(self, y: float, v: float, force: float, h: float):
        """No friction: one exact step of the linear cart under the constant force [N]."""
        if h <= 0.0:
            return y, v
        return self._slip(y, v, force / self.m, h)

    def _advance(self, y: float, v: float, force: float, h: float):
        """One piece with stick-slip: (y, y') at its start -> after h [s] under ``force`` [N]."""
        if h <= 0.0:
            return y, v
        left = h
        for _ in range(_MAX_EVENTS):
            if v == 0.0:
                if -self.break_left <= force <= self.break_right:
                    return y, 0.0  # stuck until the drive changes at the next sample
                s = 1.0 if force > 0.0 else -1.0
            else:
                s = 1.0 if v > 0.0 else -1.0
            b = (force - s * (self.f_right if s > 0.0 else self.f_left)) / self.m
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


def _rk4_closure(accel):
    """``rk4(y, yd, h)``: one classical RK4 step of y'' = accel(y, y'), in
    :meth:`_GeneralCart._rk4`'s arithmetic and order."""

    def rk4(y, yd, h):
        half = 0.5 * h
        a1 = accel(y, yd)
        v2 = yd + half * a1
        a2 = accel(y + half * yd, v2)
        v3 = yd + half * a2
        a3 = accel(y + half * v2, v3)
        v4 = yd + h * a3
        a4 = accel(y + h * v3, v4)
        sixth = h / 6
        return (
            y + sixth * (yd + 2 * v2 + 2 * v3 + v4),
            yd + sixth * (a1 + 2 * a2 + 2 * a3 + a4),
        )

    return rk4


class _GeneralCart:
    """The cart under any force effects: classical RK4 on fine sub-steps (Ts/5), with the
    stick-slip events of dry friction located by bisection and the Karnopp stick test at each.

    Used where the closed form does not apply (a spring, friction that varies along the track
    or with the speed: Stribeck's). Forces keep their hard forms: no smoothing anywhere. Within
    a slip phase the friction direction is fixed, so the right-hand side is smooth and RK4
    converges at fourth order; the error is below 2e-11 m over a run at these time scales
    (:data:`jaxcart.substeps.RK4_SUBSTEPS`; tested against the closed form where both
    apply). Where every force is affine (a spring) a piece of a sample without an event is the
    sub-steps composed into one map (:func:`_rk4_map`).
    """

    def __init__(self, m, c, gamma, drive, friction, others, h, substeps):
        self.m, self.c, self.gamma, self.drive, self.h = m, c, gamma, drive, h
        self.substeps = substeps
        self.friction, self.others = friction, others
        # Friction that varies neither along the track nor with the speed is one number per
        # direction within a slip phase.
        self.varying = friction.varying
        self.affine = None if self.varying else _affine_phase(m, c, drive, others, h)
        self.maps: dict = {}

    def _kinetic(self, s):
        """The constant friction level [N] sliding in direction s (not ``varying``)."""
        right, left = self.friction.constant
        return right if s > 0.0 else left

    def _stepper(self, v, s):
        """``rk4(y, yd, h)``: :meth:`_rk4` under the held voltage ``v`` [V] and friction
        direction ``s``, the same arithmetic in the same order (bit for bit), with what is
        constant over the phase computed once: this is the simulator's inner loop."""
        m, c, drive = self.m, self.c, self.drive
        forces = tuple(e.exact_force_for(drive) for e in self.others)
        if self.varying:
            gv, level = self.gamma * v, self.friction.level

            def accel(y, yd):
                f = gv - c * yd - s * level(y, s, abs(yd))
                for force in forces:
                    f += force(y, yd, v)
                return f / m

            return _rk4_closure(accel)
        gv, sk = self.gamma * v, s * self._kinetic(s)

        if len(forces) == 1:
            (force,) = forces

            def accel(y, yd):
                return (gv - c * yd - sk + force(y, yd, v)) / m

        else:

            def accel(y, yd):
                f = gv - c * yd - sk
                for force in forces:
                    f += force(y, yd, v)
                return f / m

        return _rk4_closure(accel)

    def _accel(self, y, yd, v, s):
        f = self.gamma * v - self.c * yd - s * self.friction.level(y, s, abs(yd))
        for e in self.others:
            f += e.exact_force(y, yd, v, self.drive)
        return f / self.m

    def _rk4(self, y, yd, v, s, h):
        a1 = self._accel(y, yd, v, s)
        y2, v2 = y + 0.5 * h * yd, yd + 0.5 * h * a1
        a2 = self._accel(y2, v2, v, s)
        y3, v3 = y + 0.5 * h * v2, yd + 0.5 * h * a2
        a3 = self._accel(y3, v3, v, s)
        y4, v4 = y + h * v3, yd + h * a3
        a4 = self._accel(y4, v4, v, s)
        return (
            y + h / 6 * (yd + 2 * v2 + 2 * v3 + v4),
            yd + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4),
        )

    def _sub_steps(self, left):
        """(n, hs [s]): the RK4 sub-steps that span ``left`` [s], at most Ts/substeps each."""
        n = max(1, math.ceil(left / self.h * self.substeps - 1e-9))
        return n, left / n

    def _map(self, h):
        """:func:`_rk4_map` of a whole piece of h [s] (a sample, or a delay's two pieces):
        made once per length."""
        got = self.maps.get(h)
        if got is None:
            if len(self.maps) >= 8:
                self.maps.clear()
            n, hs = self._sub_steps(h)
            got = self.maps[h] = _rk4_map(self.affine[0], hs, n)
        return got

    def advance(self, y: float, yd: float, v: float, h: float):
        """(y, y') after h [s] under the held voltage v [V]: a piece with no event in one
        affine map where the forces allow (:func:`_affine_phase`), else RK4 sub-steps."""
        left = h
        friction = bool(self.friction.dry)
        for _ in range(_MAX_EVENTS):
            if left <= 0.0:
                return y, yd
            if friction and yd == 0.0:
                applied = self.gamma * v + sum(
                    e.exact_force(y, 0.0, v, self.drive) for e in self.others
                )
                if self.friction.stuck(y, applied):
                    return y, 0.0  # stuck: every force is constant while y is
                s = 1.0 if applied > 0.0 else -1.0
            else:
                s = 1.0 if yd > 0.0 else -1.0
            if self.affine is not None and left == h:
                p00, p01, p10, p11, q0, q1 = self._map(h)
                acc = (self.gamma * v - s * self._kinetic(s) + self.affine[1]) / self.m
                y1, yd1 = p00 * y + p01 * yd + q0 * acc, p10 * y + p11 * yd + q1 * acc
                if not friction or yd1 * s > 0.0:
                    return y1, yd1
                # The velocity reached 0 in this sample: the sub-steps below find when.
            n, hs = self._sub_steps(left)
            rk4 = self._stepper(v, s)
            for i in range(n):
                y1, yd1 = rk4(y, yd, hs)
                if friction and yd1 * s <= 0.0:
                    # Velocity reached 0 inside this sub-step: find when, stop there.
                    lo, hi = 0.0, hs
                    for _ in range(60):
                        mid = 0.5 * (lo + hi)
                        if rk4(y, yd, mid)[1] * s > 0.0:
                            lo = mid
                        else:
                            hi = mid
                    y = rk4(y, yd, hi)[0]
                    yd = 0.0
                    left -= i * hs + hi
                    break
                y, yd = y1, yd1
            else:
                return y, yd
        raise RuntimeError(f"more than {_MAX_EVENTS} stick-slip events in one sample")


def _affine_phase(m, c, drive, others, h):
    """(A, f0 [N]) where every force of ``others`` is affine in (y, y')
    (:meth:`jaxcart.effects.base.Effect.exact_affine`), else None: within a slip phase
    x = (y, y') then obeys x' = A x + (0, a), a = (gamma v - s f_k + f0)/m [m/s^2] constant.

    Its velocity could reach 0 inside a sample and come back only if the phase oscillates
    within a sample, which a check at the sample's end would miss: None unless half the
    damped period pi/w is over 2 h (springs up to ~6e5 N/m on a 1 kg cart at Ts = 2 ms)."""
    affine = [e.exact_affine(drive) for e in others]
    if not affine or any(a is None for a in affine):
        return None
    k_y, k_yd, f0 = (float(sum(a[i] for a in affine)) for i in range(3))
    mat = np.array([[0.0, 1.0], [k_y / m, (k_yd - c) / m]])
    half_trace, det = 0.5 * mat[1, 1], -mat[1, 0]
    if det > half_trace**2 and math.pi / math.sqrt(det - half_trace**2) <= 2 * h:
        return None
    return mat, f0


def _rk4_map(mat, hs, n):
    """(p00, p01, p10, p11, q0, q1): ``n`` RK4 sub-steps of length ``hs`` [s] of x' = A x +
    (0, a) as one affine map x -> P x + q a. RK4 on a linear system is exactly affine: a
    sub-step is x -> R x + hs S (0, a) with Z = hs A, R = I + Z + Z^2/2 + Z^3/6 + Z^4/24,
    S = I + Z/2 + Z^2/6 + Z^3/24; so the map gives the sub-steps' numbers up to rounding
    (1e-16 relative)."""
    z = hs * mat
    eye = np.eye(2)
    z2 = z @ z
    z3 = z2 @ z
    r = eye + z + z2 / 2 + z3 / 6 + z3 @ z / 24
    step = hs * (eye + z / 2 + z2 / 6 + z3 / 24)[:, 1]
    p, q = eye, np.zeros(2)
    for _ in range(n):
        p, q = r @ p, r @ q + step
    return (*(float(x) for x in p.ravel()), float(q[0]), float(q[1]))


class _VelocityCart:
    """The cart under dry friction that does not vary along the track and force effects that
    are piecewise linear in the velocity alone (a current limit): the closed form of
    :class:`_Cart` within each piece, and the events in closed form too.

    At a held voltage v the force of the effects is F(y') = f0_j + k_j y' on the j-th interval
    of the velocity (:meth:`jaxcart.effects.base.Effect`'s ``exact_velocity_pieces``), and
    continuous, so within a piece and a slip direction s the motion is y'' = -a y' + b with
    a = (c - k_j)/m, b = (gamma v - s f_k,s + f0_j)/m (f_k,s the kinetic level sliding in
    direction s), and y' runs monotonically towards b/a.
    The next event is the nearest break between y' and b/a (a new piece) or, under friction,
    y' = 0 (the Karnopp stick test); its time is :func:`_stop_time` of the velocity shifted
    by the break. Agrees with :class:`_GeneralCart`'s RK4 to ~1e-12 m (tests/test_exact.py)
    at a tenth of its cost or less.
    """

    def __init__(self, m, c, gamma, drive, friction, others):
        self.m, self.c, self.gamma, self.drive = m, c, gamma, drive
        self.others = others
        self.friction = bool(friction.dry)
        self.f_right, self.f_left = friction.constant
        self.stuck = friction.stuck
        self._at: dict = {}
        self._phis: dict = {}

    def _law(self, v):
        """(breaks, pieces) of all the effects together at the held voltage v [V]."""
        law = self._at.get(v)
        if law is not None:
            return law
        each = [e.exact_velocity_pieces(self.drive, v) for e in self.others]
        if len(each) == 1 and all(a < b for a, b in itertools.pairwise(each[0][0])):
            # One effect, its breaks in order: its own pieces (as the union below makes them).
            law = (tuple(each[0][0]), tuple((0.0 + g0, 0.0 + g) for g0, g in each[0][1]))
            return self._remember(v, law)
        breaks = sorted({b for bs, _ in each for b in bs})
        # A velocity inside each interval of the union tells which piece of each effect acts.
        inner = [0.5 * (lo + hi) for lo, hi in zip(breaks, breaks[1:], strict=False)]
        probes = [breaks[0] - 1.0, *inner, breaks[-1] + 1.0] if breaks else [0.0]
        pieces = []
        for x in probes:
            f0 = k = 0.0
            for bs, ps in each:
                g0, g = ps[bisect.bisect_right(bs, x)]
                f0, k = f0 + g0, k + g
            pieces.append((f0, k))
        return self._remember(v, (tuple(breaks), tuple(pieces)))

    def _remember(self, v, law):
        if len(self._at) >= 8:  # a sample holds one or two voltages: the last few suffice
            self._at.clear()
        self._at[v] = law
        return law

    def advance(self, y: float, yd: float, v: float, h: float):
        """(y, y') after h [s] under the held voltage v [V]."""
        breaks, pieces = self._law(v)
        gv, left = self.gamma * v, h
        for _ in range(_MAX_EVENTS):
            if left <= 0.0:
                return y, yd
            s = 0.0
            if self.friction:
                if yd == 0.0:
                    f0, _ = pieces[bisect.bisect_right(breaks, 0.0)]
                    applied = gv + f0
                    if self.stuck(y, applied):
                        return y, 0.0  # stuck: every force is constant while y is
                    s = 1.0 if applied > 0.0 else -1.0
                else:
                    s = 1.0 if yd > 0.0 else -1.0
            j = bisect.bisect_right(breaks, yd)
            a, b = self._phase(pieces[j], gv, s)
            if j > 0 and yd == breaks[j - 1] and b - a * yd < 0.0:
                j -= 1  # on a break and slowing: the piece below
                a, b = self._phase(pieces[j], gv, s)
            ve = self._event(breaks, j, yd, b - a * yd, s != 0.0)
            if ve is not None and (ve - yd) * (b - a * ve) > 0.0:
                t_e = _stop_time(a, yd - ve, b - a * ve)
                if t_e < left:
                    _, p1, p2 = _phis(a, t_e)
                    y, yd, left = y + p1 * yd + p2 * b, ve, left - t_e
                    continue
            e, p1, p2 = self._whole(a, h) if left == h else _phis(a, left)
            y_end, yd_end = y + p1 * yd + p2 * b, e * yd + p1 * b
            if ve is not None and (yd_end - ve) * (yd - ve) < 0.0:
                yd_end = ve  # rounding only: y' does not pass the event it did not reach
            return y_end, yd_end
        raise RuntimeError(f"more than {_MAX_EVENTS} events in one sample")

    def _whole(self, a, h):
        """:func:`_phis` of a whole piece (a piece's ``a`` and a sample's length repeat)."""
        got = self._phis.get((a, h))
        if got is None:
            if len(self._phis) >= 16:
                self._phis.clear()
            got = self._phis[(a, h)] = _phis(a, h)
        return got

    def _phase(self, piece, gv, s):
        """(a [1/s], b [m/s^2]) of y'' = -a y' + b on ``piece`` in slip direction s."""
        f0, k = piece
        f_k = self.f_right if s > 0.0 else self.f_left
        return (self.c - k) / self.m, (gv - s * f_k + f0) / self.m

    @staticmethod
    def _event(breaks, j, yd, accel, friction):
        """The nearest event velocity [m/s] ahead of y' in the direction it moves (a break of
        piece j, or 0 under friction), or None."""
        if accel > 0.0:
            ahead = [breaks[j]] if j < len(breaks) else []
            ahead += [0.0] if friction and yd < 0.0 else []
            return min(ahead) if ahead else None
        if accel < 0.0:
            ahead = [breaks[j - 1]] if j > 0 else []
            ahead += [0.0] if friction and yd > 0.0 else []
            return max(ahead) if ahead else None
        return None


class _BacklashCart:
    """Cart and motor side joined through backlash (:mod:`jaxcart.effects.backlash`): three
    modes (free, contact on either side), classical RK4 on fine sub-steps (Ts/5) within a mode,
    and every event located by bisection: impact (|d| = b/2; inelastic, momentum shared),
    separation (the contact force N turns to pull) and the cart's stick-slip (Karnopp). No
    smoothing anywhere. Holds the play's state (d [m], d' [m/s], mode) across samples.
    """

    MAX_EVENTS = 16

    def __init__(self, plant, effect, gamma, drive, friction, others, h, substeps):
        self.substeps = substeps
        self.big_m, self.m_j = float(plant.M), float(plant.M_J)
        self.m = self.big_m + self.m_j
        self.b_eq, self.b_emf = float(plant.B_eq), float(plant.B_emf)
        self.c = self.b_eq + self.b_emf
        self.gamma, self.drive, self.h = gamma, drive, h
        self.half = 0.5 * float(effect.backlash)
        self.friction, self.others = friction, others
        self.dry = bool(friction.dry)
        self.d, self.dd, self.mode = effect.exact_init(h)

    def _kinetic(self, y, yd, s):
        return self.friction.level(y, s, abs(yd)) if self.dry else 0.0

    def _other(self, y, yd, v):
        return sum(e.exact_force(y, yd, v, self.drive) for e in self.others)

    def _rhs(self, x, v, s):
        """(y', y'', d', d'') with the friction direction s (0: the cart is stuck)."""
        y, yd, d, dd = x
        if s == 0.0:
            cart = 0.0
        elif self.mode:
            friction = s * self._kinetic(y, yd, s)
            cart = self.gamma * v - self.c * yd - friction + self._other(y, yd, v)
            return yd, cart / self.m, 0.0, 0.0
        else:
            friction = s * self._kinetic(y, yd, s)
            cart = (-self.b_eq * yd - friction + self._other(y, yd, v)) / self.big_m
        if self.mode:
            return yd, 0.0, 0.0, 0.0
        motor = (self.gamma * v - self.b_emf * (yd + dd)) / self.m_j
        return yd, cart, dd, motor - cart

    def _contact(self, x, v, s):
        """Contact force of the pinion on the rack N [N] (motor's equation), joined mode."""
        if s == 0.0:
            return self.gamma * v  # both at rest: the motor's whole drive goes into the rack
        accel = self._rhs(x, v, s)[1]
        return self.gamma * v - self.b_emf * x[1] - self.m_j * accel

    def _rk4(self, x, v, s, h):
        k1 = self._rhs(x, v, s)
        k2 = self._rhs(tuple(a + 0.5 * h * k for a, k in zip(x, k1, strict=True)), v, s)
        k3 = self._rhs(tuple(a + 0.5 * h * k for a, k in zip(x, k2, strict=True)), v, s)
        k4 = self._rhs(tuple(a + h * k for a, k in zip(x, k3, strict=True)), v, s)
        return tuple(
            a + h / 6 * (p + 2 * q + 2 * r + w)
            for a, p, q, r, w in zip(x, k1, k2, k3, k4, strict=True)
        )

    def _event(self, x, v, s):
        """True once an event has happened at state x (within the current phase)."""
        if self.dry and s != 0.0 and s * x[1] <= 0.0:
            return True  # the cart's velocity reached 0
        if self.mode == 0:
            return abs(x[2]) >= self.half  # the gap closed
        return self.mode * self._contact(x, v, s) < 0.0  # the pinion would pull: separation

    def _direction(self, x, v):
        """Friction direction of the phase: sign(y'), or at rest the Karnopp test (0: stuck)."""
        y, yd = x[0], x[1]
        if yd != 0.0 or not self.dry:
            return 1.0 if yd >= 0.0 else -1.0
        applied = self._other(y, 0.0, v) + (self.gamma * v if self.mode else 0.0)
        if self.friction.stuck(y, applied):
            return 0.0
        return 1.0 if applied > 0.0 else -1.0

    def advance(self, y: float, yd: float, v: float, h: float):
        """(y, y') after h [s] under the held voltage v [V]; the play's state moves along."""
        x = (y, yd, self.d, self.dd)
        left = h
        for _ in range(self.MAX_EVENTS):
            if left <= 0.0:
                break
            s = self._direction(x, v)
            if self.mode and self.mode * self._contact(x, v, s) < 0.0:
                # Separation: the motor leaves the rack (with no play, for the other side).
                self.mode = 0.0 if self.half > 0.0 else -self.mode
                continue
            if self.mode and s == 0.0:
                break  # joined and stuck: every force is constant until the next sample
            n = max(1, math.ceil(left / self.h * self.substeps - 1e-9))
            hs = left / n
            for i in range(n):
                x1 = self._rk4(x, v, s, hs)
                if self._event(x1, v, s):
                    lo, hi = 0.0, hs
                    for _ in range(60):
                        mid = 0.5 * (lo + hi)
                        if self._event(self._rk4(x, v, s, mid), v, s):
                            hi = mid
                        else:
                            lo = mid
                    x = self._apply_event(self._rk4(x, v, s, hi), s)
                    left -= i * hs + hi
                    break
                x = x1
            else:
                break
        else:
            raise RuntimeError(f"more than {self.MAX_EVENTS} backlash events in one sample")
        self.d, self.dd = x[2], x[3]
        return x[0], x[1]

    def _apply_event(self, x, s):
        """The state just after the event found at x (a separation needs nothing here: the
        next phase's contact test sees it)."""
        y, yd, d, dd = x
        if self.dry and s != 0.0 and s * yd <= 0.0:
            yd, dd = 0.0, dd + yd  # the cart stops; the motor side keeps its velocity
        if self.mode == 0 and abs(d) >= self.half:
            side = 1.0 if d > 0.0 else -1.0
            yd = (self.big_m * yd + self.m_j * (yd + dd)) / self.m  # inelastic: momentum shared
            d, dd, self.mode = side * self.half, 0.0, side
        return y, yd, d, dd


class _Drive(NamedTuple):
    """The motor's constants as floats, for the exact forms of force effects."""

    gamma: float
    Rm: float
    B_emf: float


def _as_floats(effect):
    """The effect with its parameters as Python floats (they may be JAX arrays)."""
    values = {}
    for name, value in effect.values().items():
        arr = np.asarray(value, dtype=float)
        values[name] = float(arr) if arr.ndim == 0 else tuple(float(v) for v in arr)
    return dataclasses.replace(effect, **values)


def supports(effect) -> bool:
    """True when the exact simulator models this effect (it has an exact form)."""
    if effect.stage == "voltage":
        return hasattr(effect, "exact")
    if effect.stage == "sensor":
        return hasattr(effect, "exact_measure")
    return (
        effect.dry_friction
        or hasattr(effect, "exact_force")
        or getattr(effect, "transmission", False)
    )


def _cart(plant: Plant, ts: float):
    """The cart's integrator: the closed form where it applies, else :class:`_GeneralCart`."""
    m, c = float(plant.m), float(plant.c)
    gamma = float(plant.gamma) if plant.motor_connected else 0.0
    forces = [_as_floats(e) for e in plant.stage("force")]
    for e in plant.effects:
        if not supports(e):
            raise NotImplementedError(
                f"effect {type(e).name} ({e!r}) has no exact form; simulate it with the "
                "smooth simulator jaxcart.simulate, or give its module an exact form"
            )
    transmission = next((e for e in forces if e.transmission), None)
    forces = [e for e in forces if e is not transmission]
    substeps = substeps_per_sample(plant, rk4=True)
    friction = _Friction([e for e in forces if e.dry_friction])
    others = [e for e in forces if not e.dry_friction]
    drive = _Drive(float(plant.gamma), float(plant.Rm), float(plant.B_emf))
    varying = friction.varying
    if transmission is not None:
        cart = _BacklashCart(plant, transmission, gamma, drive, friction, others, ts, substeps)
    elif others and not varying and all(hasattr(e, "exact_velocity_pieces") for e in others):
        cart = _VelocityCart(m, c, gamma, drive, friction, others)
    elif others or varying:
        cart = _GeneralCart(m, c, gamma, drive, friction, others, ts, substeps)
    else:
        cart = _Cart(m, c, friction, ts)
        return _pieces(cart.advance, ts, scale=gamma)
    return _pieces(cart.advance, ts)


def _pieces(advance, ts, scale=None):
    """``step(y, y', early, late, split)``: (y, y') a sample later, over the sample's one or two
    held-voltage pieces (``early`` [V] for ``split`` [s], then ``late``); ``advance(y, y', x,
    h)`` takes the voltage, or the force ``scale`` * voltage [N] where ``scale`` is given."""
    if scale is None:

        def step(y, v, early, late, split):
            if split > 0.0:
                y, v = advance(y, v, early, split)
            return advance(y, v, late, ts - split)

    else:

        def step(y, v, early, late, split):
            if split > 0.0:
                y, v = advance(y, v, scale * early, split)
            return advance(y, v, scale * late, ts - split)

    return step


def _sensors(plant: Plant, ts: float):
    """``measure(y) -> y_read``: the sensor stage, its state carried; None without sensors."""
    sensors = [_as_floats(e) for e in plant.stage("sensor")]
    if not sensors:
        return None
    states = [e.exact_init(ts) for e in sensors]

    def measure(y):
        for i, e in enumerate(sensors):
            y, states[i] = e.exact_measure(states[i], y)
        return y

    return measure


def _pid_start(controller: PID, r0: float, y0: float, plant: Plant, ts: float):
    """(the PID on floats, its state before the first sample). The controller's first read
    goes through sensors of its own, so that it advances no state of the loop's."""
    pid = float_pid(controller)
    first = _sensors(plant, ts)
    y_first = y0 if first is None else first(y0)
    state = PIDState(*(float(s) for s in pid_init(pid, r0, y_first, xp=np)))
    return pid, state


def _voltage_stage(plant: Plant, ts: float):
    """``stage(u) -> (early, late, split)``: the voltage effects on the command u [V] held
    over a sample, their state carried; None without voltage effects."""
    voltages = [_as_floats(e) for e in plant.stage("voltage")]
    if not voltages:
        return None
    states = [e.exact_init(ts) for e in voltages]

    def stage(u):
        held = Held(u, u, 0.0)
        for i, e in enumerate(voltages):
            held, states[i] = e.exact(states[i], held, ts)
        return float(held.early), float(held.late), float(held.split)

    return stage


# ---------------------------------------------------------------- the loop


def simulate_exact(plant: Plant, controller: PID | None, experiment: Experiment) -> Response:
    """Simulate one experiment exactly (hard forms, event-exact stick-slip); numpy float64.

    plant: :class:`jaxcart.Plant` with any effects that have an exact form (every registered
    effect does). controller: :class:`jaxcart.PID` for closed-loop experiments (ignored
    otherwise, may be None). experiment: :class:`jaxcart.Experiment`.

    Returns a :class:`jaxcart.Response` with the fields of :func:`jaxcart.simulate`: time t_k [s],
    position [m] (what the sensor reports: y_k after the sensor effects) and velocity y'_k
    [m/s], reference r_k [m], error r_k - position [m], command u_k [V] (after the software
    limit), voltage [V] (after the voltage effects, the piece held at the end of the sample),
    unlimited v_k [V] (the controller output before any limit), diverged (bool; from the first
    sample with |y| > DIVERGED_POSITION or not finite the simulation stops and the later samples
    are nan), kind.
    """
    check_run(plant, controller, experiment)
    ts = float(experiment.sample_time)
    kind = experiment.kind
    closed = kind == "closed_loop"
    advance = _cart(plant, ts)
    signal = np.asarray(experiment.signal, dtype=np.float64)
    n = signal.shape[-1]
    y0 = float(experiment.y0)
    measure = _sensors(plant, ts)
    pid = _pid_start(controller, float(signal[0]), y0, plant, ts) if closed else None
    rows = _loop(advance, measure, pid, _voltage_stage(plant, ts), signal.tolist(), experiment)
    position, velocity, command, voltage, unlimited = (np.full(n, np.nan) for _ in range(5))
    for out, got in zip((position, velocity, command, voltage, unlimited), rows, strict=True):
        out[: len(got)] = got
    # A diverged run records the state it stopped at, but no command for that sample.
    diverged = len(rows[2]) < len(rows[0])
    reference = signal.copy() if closed else np.full(n, y0)
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


def _loop(advance, measure, pid_start, voltage_stage, signal: list, experiment: Experiment):
    """The sampled loop on Python floats: lists of the sensor's position [m], velocity [m/s],
    command u_k [V], voltage [V] and unlimited v_k [V], one entry a sample; a run that
    diverges stops with its state recorded and no command for that sample. ``pid_start``:
    :func:`_pid_start`'s (controller, state) of a closed loop, else None."""
    n = len(signal)
    open_loop = experiment.kind == "open_loop"
    y, v = float(experiment.y0), float(experiment.yd0)
    position, velocity, command, voltage, unlimited = [], [], [], [], []
    control = None
    if pid_start is not None:
        pid, state = pid_start
        control = pid_stepper(pid, Floats, float_clip)
    for k in range(n):
        if not abs(y) <= DIVERGED_POSITION:  # also catches nan
            position.append(y)
            velocity.append(v)
            break
        y_read = y if measure is None else measure(y)
        if control is not None:
            u, raw, state = control(state, signal[k], y_read)
        elif open_loop:
            u = raw = signal[k]
        else:
            u = raw = 0.0
        if voltage_stage is None:
            early = late = u
            split = 0.0
        else:
            early, late, split = voltage_stage(u)
        position.append(y_read)
        velocity.append(v)
        command.append(u)
        voltage.append(late)
        unlimited.append(raw)
        if k + 1 < n:
            y, v = advance(y, v, early, late, split)
    return position, velocity, command, voltage, unlimited


def step_info_exact(plant: Plant, controller: PID, experiment: Experiment) -> StepInfo:
    """:func:`jaxcart.metrics.step_info` of the exact run (saturation against
    :func:`voltage_limit`)."""
    response = simulate_exact(plant, controller, experiment)
    return step_info(response, v_limit=voltage_limit(plant, controller))
