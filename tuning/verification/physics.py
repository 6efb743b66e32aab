"""The independent generator's continuous physics: the drive chain, its own friction convention
and its integrator. Written apart from jaxcart's simulators (it shares no code with
``jaxcart/exact.py``, ``jaxcart/smooth_sim.py`` or ``jaxcart/effects/``), from the equations:

    command u(t) [V] (held, delayed) -> gain(t) u + v_offset + offset(t) -> dead band -> lag w
      -> saturation -> gamma_scale -> motor: i = clip((V - Km Kg y' / r_mp) / Rm, +-i_max)
    m y'' = F_drive + F_ext(t, y) - B_dir y' - friction
      F_drive = eta_g Kg eta_m Kt / r_mp * i,  F_ext = -k_s (y - y_rest) + f_tilt + push(t)

Friction (Karnopp with a zero-velocity band ``v_band``): a cart with |y'| <= v_band counts as at
rest; it stays stuck (y' = 0, y held) while the force on it (all but friction, at y' = 0) is
within the breakaway level towards that force, S = max(f_s, K); else it slides on (towards the
force, or against it until its velocity reverses). Sliding in direction d,
friction is d (K + (S - K) exp(-(y'/v_stribeck)^2)), K = the kinetic level of that direction
plus the track's table at y and the rise with speed, rise_d (1 - exp(-|y'| / v_rise)): from S at
breakaway down to K (v_stribeck = 0: at once, the lurch).
Viscous friction B_dir y' takes the direction's value.

Integrator: classical RK4 on (y, y') on a fixed sub-step (``SUBSTEPS`` = 40 a sample, 25 us at
1 ms), the friction direction (or the stuck state) frozen within a sub-step, so its right-hand
side is smooth there. Every instant where the held command or a push changes is a sub-step
boundary (a sample is cut into pieces at them, each into equal sub-steps no longer than
Ts / SUBSTEPS). The amplifier's lag is solved in closed form over a piece (its input is held
there): w(t) = w_in + (w_0 - w_in) exp(-(t - t_0) / lag). Where the law changes within a
sub-step (the velocity enters the band or crosses zero, the voltage or the current reaches its
limit: located by linear interpolation; a stuck cart's force reaches the breakaway level:
located by regula falsi) the sub-step is integrated again up to that instant and the rest
begun from there, so that no result depends on where the sub-step grid falls. Halving the
sub-step moves a run's positions by less than 1e-8 m (``tests/test_independent_sim.py``; on a
4.5 s ramp that breaks away late, 40 -> 80 sub-steps moved them by 2e-9 m).
"""

from __future__ import annotations

import math

from tuning.verification.truth import TrueCart

#: RK4 sub-steps per sample (the largest sub-step is Ts / SUBSTEPS).
SUBSTEPS = 40
#: Pieces of a sample shorter than this [s] are not integrated (rounding of event times).
_TINY = 1e-13
#: Events located within one sub-step, at most (each splits what is left of it).
_MAX_EVENTS = 4
#: Regula falsi iterations that locate a breakaway within a sub-step.
_REFINE = 6
#: An event closer than this share of a sub-step to either end is left where it falls.
_SPLIT = 1e-9


class Cart:
    """The cart in motion: ``advance`` integrates its state (y [m], y' [m/s], w [V]: the
    amplifier's lagged output, before saturation) under a held command.

    truth: the :class:`TrueCart`; lag: the amplifier's time constant [s] (truth's plus any
    artefact's); wander: ``f(t) -> (gain, offset [V])`` of the drive's slow drift, or None
    (evaluated once a piece, at its middle: it moves by microvolts over a sample); push:
    ``f(t) -> force [N]`` of a hand's push, or None; substeps: RK4 sub-steps a sample of
    ``sample_time`` [s].
    """

    def __init__(
        self,
        truth: TrueCart,
        *,
        sample_time: float,
        lag: float | None = None,
        wander=None,
        push=None,
        substeps: int = SUBSTEPS,
    ):
        if substeps < 1:
            raise ValueError("substeps must be >= 1")
        self.truth = truth
        self.h_max = sample_time / substeps
        lag = truth.lag if lag is None else lag
        self.inv_lag = 1.0 / lag if lag > 0 else 0.0
        self.wander, self.push = wander, push
        self.m = truth.m
        self.dz_pos, self.dz_neg = truth.dead_band()
        # The drive's constants, bound once: forces() runs four times a sub-step.
        self.connected = truth.motor_connected
        self.kf, self.ke = truth.force_per_amp, truth.emf_per_speed
        self.inv_rm, self.vsat, self.imax = 1.0 / truth.Rm, truth.v_sat, truth.i_max
        self.gs = truth.gamma_scale
        self.limited = self.connected and (math.isfinite(self.vsat) or math.isfinite(self.imax))
        self.b_pos, self.b_neg = truth.viscous(+1), truth.viscous(-1)
        self.band, self.v_st = truth.v_band, truth.v_stribeck
        self.stribeck = truth.v_stribeck > 0 and truth.f_s is not None
        self.rises = bool(truth.rise_pos or truth.rise_neg)
        self.varying = self.stribeck or self.rises or bool(truth.track_y)
        self.kinetic_pos, self.kinetic_neg = truth.kinetic(+1), truth.kinetic(-1)
        self.f_tilt, self.k_s, self.y_rest = truth.f_tilt, truth.k_s, truth.y_rest

    # ------------------------------------------------------------ forces

    def amplifier_input(self, t: float, command: float) -> float:
        """The voltage into the amplifier's lag stage at t for a held ``command`` [V]:
        gain and offset (with their drift), then the dead band."""
        v = command + self.truth.v_offset
        if self.wander is not None:
            gain, offset = self.wander(t)
            v = gain * command + self.truth.v_offset + offset
        if v > self.dz_pos:
            return v - self.dz_pos
        if v < -self.dz_neg:
            return v + self.dz_neg
        return 0.0

    def volts(self, drive, t: float) -> float:
        """The amplifier's lagged output at t [V]; ``drive`` = (t_0 [s], w_0 [V], input [V])."""
        t0, w0, vin = drive
        if not self.inv_lag:
            return vin
        return vin + (w0 - vin) * math.exp(-(t - t0) * self.inv_lag)

    def current(self, volts: float, speed: float) -> float:
        """The armature current [A] before its limit, at the lagged output ``volts`` [V]."""
        limit = self.vsat
        volts = limit if volts > limit else (-limit if volts < -limit else volts)
        return (self.gs * volts - self.ke * speed) * self.inv_rm

    def forces(self, t: float, y: float, speed: float, volts: float) -> float:
        """Every force on the cart but friction [N] at the amplifier's lagged output ``volts``
        [V]: the motor (saturation, drive gain, armature current with its limit), the spring,
        the tilt and the push."""
        force = self.f_tilt - self.k_s * (y - self.y_rest)
        if self.connected:
            limit = self.imax
            current = self.current(volts, speed)
            current = limit if current > limit else (-limit if current < -limit else current)
            force += self.kf * current
        if self.push is not None:
            force += self.push(t)
        return force

    def friction(self, d: int, y: float, speed: float) -> float:
        """Friction's magnitude sliding in direction ``d`` at ``speed`` = |y'| [m/s] [N]:
        the Stribeck curve from the breakaway level to the kinetic one, and the rise to a
        plateau."""
        if not self.varying:
            return self.kinetic_pos if d > 0 else self.kinetic_neg
        truth = self.truth
        kinetic = truth.kinetic(d, y) + (truth.rise(d, speed) if self.rises else 0.0)
        if not self.stribeck:
            return kinetic
        breakaway = truth.static(d, y)
        return kinetic + (breakaway - kinetic) * math.exp(-((speed / self.v_st) ** 2))

    def _accel(self, t, y, v, drive, d):
        """y'' [m/s^2] sliding in direction ``d``."""
        force = self.forces(t, y, v, self.volts(drive, t))
        if d > 0:
            force -= self.b_pos * v + self.friction(1, y, v)
        else:
            force -= self.b_neg * v - self.friction(-1, y, -v)
        return force / self.m

    # ------------------------------------------------------------ events

    def _excess(self, t, y, drive) -> float:
        """How far the force on the cart at rest is beyond its breakaway level [N]."""
        force = self.forces(t, y, 0.0, self.volts(drive, t))
        return abs(force) - self.truth.static(1 if force > 0 else -1, y)

    def _breakaway(self, t, y, drive, h) -> float | None:
        """The fraction of a sub-step at which a stuck cart's force reaches its breakaway level
        (regula falsi, Illinois: the cart is held, so the force is known in closed form), or
        None."""
        lo, hi = 0.0, 1.0
        g_lo, g_hi = self._excess(t, y, drive), self._excess(t + h, y, drive)
        if not (g_lo <= 0 < g_hi):
            return None
        for _ in range(_REFINE):
            mid = lo + (hi - lo) * g_lo / (g_lo - g_hi)
            g = self._excess(t + mid * h, y, drive)
            if g > 0:
                hi, g_hi, g_lo = mid, g, g_lo / 2
            else:
                lo, g_lo, g_hi = mid, g, g_hi / 2
        return hi if _SPLIT < hi < 1.0 - _SPLIT else None

    def _limits(self, t, v, drive) -> tuple:
        """(|voltage| - v_sat [V], |current| - i_max [A]): where each changes sign, the drive's
        law has a corner."""
        volts = self.volts(drive, t)
        return abs(volts) - self.vsat, abs(self.current(volts, v)) - self.imax

    @staticmethod
    def _event(before, after):
        """(fraction of a sub-step strictly inside it, index) of the first of the indicators to
        change sign, by linear interpolation; None if none does."""
        first = None
        for i, (g0, g1) in enumerate(zip(before, after, strict=True)):
            if (g0 > 0) != (g1 > 0) and math.isfinite(g0) and math.isfinite(g1):
                theta = g0 / (g0 - g1)
                if _SPLIT < theta < 1.0 - _SPLIT and (first is None or theta < first[0]):
                    first = (theta, i)
        return first

    # ------------------------------------------------------------ the integrator

    def _rk4(self, t, y, v, drive, h, d):
        accel = self._accel
        h2 = 0.5 * h
        a1 = accel(t, y, v, drive, d)
        a2 = accel(t + h2, y + h2 * v, v + h2 * a1, drive, d)
        v2 = v + h2 * a1
        a3 = accel(t + h2, y + h2 * v2, v + h2 * a2, drive, d)
        v3 = v + h2 * a2
        a4 = accel(t + h, y + h * v3, v + h * a3, drive, d)
        v4 = v + h * a3
        s = h / 6.0
        return y + s * (v + 2 * v2 + 2 * v3 + v4), v + s * (a1 + 2 * a2 + 2 * a3 + a4)

    def _direction(self, t, y, v, drive, in_band):
        """Karnopp: the slip direction for a sub-step from (y, v) (0: stuck), and the velocity
        to start it from (0 when stuck)."""
        if abs(v) > self.band and not in_band:
            return (1 if v > 0 else -1), v
        force = self.forces(t, y, 0.0, self.volts(drive, t))
        d = 1 if force > 0 else -1
        if abs(force) <= self.truth.static(d, y):
            return 0, 0.0
        if v * d < 0:  # moving against a force beyond the static level: on to its reversal
            return -d, v
        return d, v

    def substep(self, t, state, vin, h, in_band=False, events=0):
        """One sub-step of length h [s] from ``state`` at t [s], amplifier input ``vin`` [V]
        held; the state at t + h. ``in_band``: the cart has just entered the band (an event)."""
        y, v, w = state
        drive = (t, w, vin)
        d, v = self._direction(t, y, v, drive, in_band)
        w1 = self.volts(drive, t + h)
        more = events < _MAX_EVENTS
        if d == 0:
            if more and (self.inv_lag or self.push is not None):  # the force may grow
                theta = self._breakaway(t, y, drive, h)
                if theta is not None:
                    return self._rest(t, (y, 0.0), drive, vin, h, theta, False, events)
            return y, 0.0, w1
        y1, v1 = self._rk4(t, y, v, drive, h, d)
        if more:
            # Entering the band (or crossing zero) and the drive's corners are events.
            edge = self.band if d * v > self.band and not in_band else 0.0
            before, after = [d * v - edge], [d * v1 - edge]
            if self.limited:
                before += self._limits(t, v, drive)
                after += self._limits(t + h, v1, drive)
            event = self._event(before, after)
            if event is not None:
                theta, which = event
                y1, v1 = self._rk4(t, y, v, drive, theta * h, d)
                entered = which == 0  # the band's edge, or zero: the stick test decides
                if entered and edge == 0.0:
                    v1 = 0.0
                return self._rest(t, (y1, v1), drive, vin, h, theta, entered, events)
        if d * v1 < 0:
            v1 = 0.0  # within the band: stopped, the next sub-step tests the rest
        return y1, v1, w1

    def _rest(self, t, moved, drive, vin, h, theta, in_band, events):
        """The rest of a sub-step after an event at fraction ``theta``."""
        t_event = t + theta * h
        state = (*moved, self.volts(drive, t_event))
        return self.substep(t_event, state, vin, (1.0 - theta) * h, in_band, events + 1)

    def advance(self, state, t0: float, t1: float, command: float):
        """The state at t1 [s] from ``state`` at t0 under the held ``command`` [V], in equal
        sub-steps no longer than the largest."""
        span = t1 - t0
        if span <= _TINY:
            return state
        vin = self.amplifier_input(t0 + 0.5 * span, command)
        n = max(1, math.ceil(span / self.h_max - 1e-9))
        h = span / n
        for i in range(n):
            state = self.substep(t0 + i * h, state, vin, h)
        return state
