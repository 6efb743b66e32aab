"""The smooth simulator: the sampled-data loop in pure JAX (jit, vmap, grad).

At each sample t_k the controller reads y_k, computes the command u_k and holds it over
[t_k, t_k+1) (zero-order hold). Between samples the cart

    m y'' + c y' = gamma * v_applied + F(y, y')

is integrated exactly for its linear part (the exponential of the 2x2 system). Where force
effects act (friction), the sample is cut into sub-steps and F is linearized in y', first at the
sub-step's start velocity, then at the end velocity that predicts (a two-stage exponential
Rosenbrock step): the stiff slope of a narrow smoothed sign() goes into the exact exponential,
so the step stays stable for any width, and a cart breaking away from rest is not held back.

>>> from jaxcart import PID, handout_plant, step, simulate
>>> res = simulate(handout_plant(), PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0), step(0.5))
>>> res.position.shape
(3001,)
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp

import jaxcart.pytrees  # noqa: F401  (PID as a pytree)
from hw.control_law import PID, pid_init, pid_update
from jaxcart.effects import Held
from jaxcart.effects.stiction import STRIBECK_SCALE
from jaxcart.experiments import Experiment
from jaxcart.params import Plant
from jaxcart.runcheck import check_run
from jaxcart.smoothing import Smoothing, smooth_clip, smooth_sign
from jaxcart.substeps import substeps_per_sample

#: |y| beyond this [m] (the track is 1 m long) or a non-finite value marks a diverged run.
DIVERGED_POSITION = 1e3
EXACT_FORMS = Smoothing(voltage=0.0, velocity=0.0, position=0.0)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Response:
    """A simulated run, sampled at t_k (arrays of shape (..., n_samples)).

    time [s]; position y_k [m]; velocity [m/s]; reference r_k [m];
    error e_k = r_k - y_k [m]; command u_k [V] (after the software limit, what the software
    sends); voltage [V] (applied to the motor, after the amplifier); diverged: True where the
    run blew up (|y| > 1 km or not finite), in which case the other fields are meaningless;
    unlimited: the controller output v_k before any limit [V] (None for recordings).
    """

    time: jax.Array
    position: jax.Array
    velocity: jax.Array
    reference: jax.Array
    error: jax.Array
    command: jax.Array
    voltage: jax.Array
    diverged: jax.Array
    unlimited: jax.Array | None = None
    kind: str = field(default="closed_loop", metadata={"static": True})


class Sample(NamedTuple):
    """What one controller period produces (before time is attached)."""

    position: jax.Array
    velocity: jax.Array
    reference: jax.Array
    command: jax.Array
    voltage: jax.Array
    unlimited: jax.Array


# ---------------------------------------------------------------- exact linear sub-step


def _phi(a, h):
    """e^{-a h}, phi1 = (1 - e^{-a h})/a and phi2 = (h - phi1)/a, stable for small a h.

    (Taylor series where |a h| < 0.1: the closed forms cancel catastrophically there.)
    """
    x = a * h
    small = jnp.abs(x) < 0.1
    xs = jnp.where(small, x, 0.0)
    xl = jnp.where(small, 1.0, x)
    em1 = -jnp.expm1(-xl)
    phi1 = jnp.where(
        small, h * (1 - xs / 2 * (1 - xs / 3 * (1 - xs / 4 * (1 - xs / 5)))), h * em1 / xl
    )
    phi2 = jnp.where(
        small,
        h * h * (0.5 - xs / 6 * (1 - xs / 4 * (1 - xs / 5 * (1 - xs / 6)))),
        h * h * (xl - em1) / (xl * xl),
    )
    return jnp.exp(-x), phi1, phi2


def _linear_step(y, yd, accel, a, h):
    """Exact solution of y'' = -a y' + accel (accel constant) over h."""
    e, phi1, phi2 = _phi(a, h)
    return y + phi1 * yd + phi2 * accel, e * yd + phi1 * accel


# ---------------------------------------------------------------- the loop


def _dry_friction(plant: Plant, smoothing: Smoothing):
    """Smoothed combined dry friction F(y, y') [N] of the plant's friction effects, or None.

    Kinetic level K(y) = sum of the members' kinetic(y); where a member differs by direction
    (``sided``), K+ and K- (each at least 0) joined by the smoothed sign s:
    K = (K+ + K-)/2 + s (K+ - K-)/2. With a static level S (stiction) the magnitude rises to S
    near zero velocity over v_s = sqrt(w c) (see :mod:`jaxcart.effects.stiction`), and over
    sqrt(v_S^2 + w c) with a Stribeck speed v_S (:mod:`jaxcart.effects.stribeck`)."""
    dry = [e for e in plant.effects if e.dry_friction]
    if not dry:
        return None
    statics = [e.static() for e in dry if e.static() is not None]
    speeds = [e.stribeck() for e in dry if e.stribeck() is not None]
    sided = any(e.sided for e in dry)
    w = smoothing.velocity

    def kinetic(y, sign):
        if not sided:
            return sum(e.kinetic(y, jnp) for e in dry)
        sides = [e.kinetic_sides(y, jnp) for e in dry]
        right = jnp.maximum(sum(r for r, _ in sides), 0.0)
        left = jnp.maximum(sum(lf for _, lf in sides), 0.0)
        return 0.5 * (right + left) + 0.5 * (right - left) * sign

    def force(y, yd):
        sign = smooth_sign(yd, w)
        level = kinetic(y, sign)
        if not statics:
            return -level * sign
        static = functools.reduce(jnp.maximum, statics)
        if speeds:
            v_s = functools.reduce(jnp.maximum, speeds)
            vs = jnp.sqrt(w * STRIBECK_SCALE + v_s * v_s)
        else:
            vs = jnp.sqrt(w * STRIBECK_SCALE)
        bump = jnp.exp(-((yd / vs) ** 2))
        return -(level + jnp.maximum(static - level, 0.0) * bump) * sign

    return force


def _transmission(plant: Plant):
    """The plant's force effect that owns the motion between samples (backlash), or None."""
    return next((e for e in plant.stage("force") if e.transmission), None)


def _total_force(plant: Plant, smoothing: Smoothing):
    """F(y, y', v) [N]: every force effect (dry friction combined), or None for none."""
    dry = _dry_friction(plant, smoothing)
    others = [e for e in plant.stage("force") if not e.dry_friction and not e.transmission]
    if dry is None and not others:
        return None

    def force(y, yd, v):
        total = dry(y, yd) if dry is not None else 0.0 * yd
        for e in others:
            total = total + e.smooth_force(y, yd, v, smoothing, plant)
        return total

    return force


def _body_step(force, m, c):
    """Returns sub(y, yd, v, drive, hs) -> (y, yd): one sub-step of a body of mass m [kg],
    damping c [kg/s] under drive [N] + force(y, y', v) [N] (exact when force is None)."""
    if force is None:
        return lambda y, yd, v, drive, hs: _linear_step(y, yd, drive / m, c / m, hs)

    def linearized(y_at, yd, about, v, drive):
        # F(w) ~ F(about) + F'(about)(w - about): the slope joins the damping, exactly.
        f0, slope = jax.jvp(lambda w: force(y_at, w, v), (about,), (jnp.ones_like(about),))
        a = (c - slope) / m
        accel = (drive + f0 - slope * about) / m
        return a, accel

    def sub(y, yd, v, drive, hs):
        # Two stages: linearized at the start velocity, then again at the velocity that
        # step predicts for the end (and forces of position at the midpoint). At breakaway
        # from rest the first slope is the huge f_c/width of the smoothed sign(); the
        # second stage lets the cart leave it within the sub-step instead of one late.
        a, accel = linearized(y, yd, yd, v, drive)
        y_end, yd_end = _linear_step(y, yd, accel, a, hs)
        a, accel = linearized(0.5 * (y + y_end), yd, yd_end, v, drive)
        return _linear_step(y, yd, accel, a, hs)

    return sub


def _backlash_sub(plant: Plant, effect, force, gamma):
    """Returns sub(y, yd, d, dd, v, hs) -> (y, yd, d, dd): one sub-step of the two-body model
    of :mod:`jaxcart.effects.backlash` (d = x_m - y [m], dd its rate [m/s])."""
    big_m, m_j = plant.M, plant.M_J
    cart = _body_step(force, big_m, plant.B_eq)
    joined = _body_step(force, plant.m, plant.c)
    a_m = plant.B_emf / m_j
    half = 0.5 * effect.backlash

    def sub(y, yd, d, dd, v, hs):
        w = yd + dd  # the motor side's velocity
        acc_m = gamma * v / m_j

        def free(t):
            # Both bodies free over t [s]: the motor in closed form, the cart its own step.
            yc, ydc = cart(y, yd, v, 0.0 * v, t)
            e, phi1, phi2 = _phi(a_m, t)
            dc = d + phi1 * w + phi2 * acc_m - (yc - y)
            return yc, ydc, dc, e * w + phi1 * acc_m

        y1, yd1, d1, w1 = free(hs)
        s = jnp.where(d1 >= 0.0, 1.0, -1.0)
        p0, p1 = s * d - half, s * d1 - half  # penetration: > 0 once the gap would close
        hit = p1 > 0.0
        # Impact time: secant on p over [0, hs] (p0 <= 0 < p1), then regula falsi steps.
        theta = jnp.clip(p0 / jnp.where(hit, p0 - p1, -1.0), 0.0, 1.0)
        for _ in range(2):
            pc = s * free(theta * hs)[2] - half
            after = pc < 0.0  # the root lies in (theta, 1]
            t_after = theta + (1.0 - theta) * (-pc) / jnp.where(after & (p1 > pc), p1 - pc, 1.0)
            t_before = theta * p0 / jnp.where(p0 - pc < 0.0, p0 - pc, -1.0)
            theta = jnp.clip(jnp.where(after, t_after, t_before), 0.0, 1.0)
        tc = jnp.where(hit, theta * hs, 0.0 * hs)
        yc, ydc, _, wc = free(tc)
        shared = (big_m * ydc + m_j * wc) / plant.m  # inelastic impact: momentum shared
        yj, ydj = joined(yc, shared, v, gamma * v, hs - tc)
        return (
            jnp.where(hit, yj, y1),
            jnp.where(hit, ydj, yd1),
            jnp.where(hit, s * half, d1),
            jnp.where(hit, 0.0 * dd, w1 - yd1),
        )

    return sub


#: Most sub-steps per sample that the force loop unrolls (jaxcart.smooth_sim._plant_step).
UNROLL_SUBSTEPS = 2


def _plant_step(plant: Plant, smoothing: Smoothing, h: float, substeps: int):
    """Returns advance(y, yd, held, extra) -> (y, yd, extra) over one sample period h [s],
    where ``held`` is the :class:`Held` voltage (one or two pieces) and ``extra`` the state of
    a transmission effect (backlash: (d, d')), () without one."""
    m, c = plant.m, plant.c
    gamma = plant.gamma if plant.motor_connected else 0.0 * plant.gamma
    force = _total_force(plant, smoothing)
    split = any(e.splits_sample for e in plant.effects)
    transmission = _transmission(plant)

    if transmission is not None:
        sub2 = _backlash_sub(plant, transmission, force, gamma)

        def piece2(y, yd, extra, v, length):
            hs = length / substeps

            def sub(_, state):
                return sub2(*state, v, hs)

            # Not unrolled: each sub-step holds four free steps, and unrolled the compile time
            # grows to minutes at 16 sub-steps.
            y, yd, d, dd = jax.lax.fori_loop(0, substeps, sub, (y, yd, *extra))
            return y, yd, (d, dd)

        def advance2(y, yd, held, extra):
            if split:
                y, yd, extra = piece2(y, yd, extra, held.early, held.split)
                return piece2(y, yd, extra, held.late, h - held.split)
            return piece2(y, yd, extra, held.late, h)

        return advance2

    if force is None:
        if not split:
            # Linear between samples: one exact step, its coefficients computed once per run.
            e, phi1, phi2 = _phi(c / m, h)

            def advance(y, yd, held, extra):
                accel = gamma * held.late / m
                return y + phi1 * yd + phi2 * accel, e * yd + phi1 * accel, extra

            return advance

        def advance(y, yd, held, extra):
            # Two exact pieces: the edge of the held voltage moved inside the sample.
            y, yd = _linear_step(y, yd, gamma * held.early / m, c / m, held.split)
            y, yd = _linear_step(y, yd, gamma * held.late / m, c / m, h - held.split)
            return y, yd, extra

        return advance

    body = _body_step(force, m, c)

    def piece(y, yd, v, length):
        hs = length / substeps
        drive = gamma * v

        def sub(_, state):
            return body(*state, v, drive, hs)

        # Unrolled up to UNROLL_SUBSTEPS: beyond, the unrolled body's compile time grows with
        # it (forward mode, 5 sub-steps: 2.0-2.4 s against 1.0-1.4 s as a loop) while the loop
        # runs within 1.3x of it; a whole cold fit of a tap 4.4 -> 2.3 s.
        return jax.lax.fori_loop(0, substeps, sub, (y, yd), unroll=substeps <= UNROLL_SUBSTEPS)

    if not split:

        def advance(y, yd, held, extra):
            return (*piece(y, yd, held.late, h), extra)

        return advance

    def advance(y, yd, held, extra):
        y, yd = piece(y, yd, held.early, held.split)
        return (*piece(y, yd, held.late, h - held.split), extra)

    return advance


class LoopState(NamedTuple):
    """The smooth loop's state between two samples (a pytree; the carry of its ``lax.scan``).

    position y [m] and velocity y' [m/s] of the cart; controller: the PID's
    :class:`hw.control_law.PIDState` (None for open-loop and tap experiments); effects: the
    sensor effects' states, then the voltage effects', in loop order; transmission: the
    transmission effect's state (backlash: the play d [m] and its rate d' [m/s]), () without
    one.
    """

    position: jax.Array
    velocity: jax.Array
    controller: object
    effects: tuple
    transmission: tuple


@dataclass(frozen=True)
class StepConfig:
    """What :func:`step` needs besides the state and the sample's signal: fixed for a run."""

    controller: PID | None
    kind: str
    y0: jax.Array
    sample_time: float
    smoothing: Smoothing
    sensors: tuple
    voltages: tuple
    advance: object  # advance(y, yd, held, extra) -> (y, yd, extra) over one period


def step(config: StepConfig, state: LoopState, signal_k) -> tuple[LoopState, Sample]:
    """One sample period of the smooth loop (pure): the sensor effects turn y_k into what the
    controller reads (and what the response records as ``position``), the controller computes
    u_k, the voltage effects turn it into the held voltage, and the cart is advanced over the
    period. ``signal_k``: r_k [m] (closed loop) or u_k [V] (open loop)."""
    n_sensors = len(config.sensors)
    sensor_states = state.effects[:n_sensors]
    voltage_states = state.effects[n_sensors:]
    y_read, sensor_states = _measure(
        config.sensors, sensor_states, state.position, config.smoothing
    )
    pid_state = state.controller
    if config.kind == "closed_loop":
        width = config.smoothing.voltage

        def clip(v, limit):
            return smooth_clip(v, limit, width)

        u, v, pid_state = pid_update(
            config.controller, pid_state, signal_k, y_read, xp=jnp, clip=clip
        )
        r = signal_k
    elif config.kind == "open_loop":
        u, v, r = signal_k, signal_k, config.y0
    else:
        u, v, r = 0.0 * signal_k, 0.0 * signal_k, config.y0
    held = Held(u, u, 0.0 * u)
    new_voltage_states = []
    for effect, st in zip(config.voltages, voltage_states, strict=True):
        held, st = effect.smooth(st, held, config.smoothing, config.sample_time)
        new_voltage_states.append(st)
    y1, yd1, extra = config.advance(state.position, state.velocity, held, state.transmission)
    z = 0 * state.position
    new = LoopState(y1, yd1, pid_state, tuple(sensor_states) + tuple(new_voltage_states), extra)
    return new, Sample(y_read, state.velocity, r + z, u + z, held.late + z, v + z)


def loop(plant, controller, experiment, *, smoothing=None, substeps=None):
    """The loop as (initial :class:`LoopState`, step function) for lax.scan over the
    experiment's signal: ``step(state, signal_k) -> (state, Sample)``, :func:`step` with the
    run's :class:`StepConfig` bound. Shared by :func:`simulate_smooth` (which stores every
    sample), the chunked simulator and the streaming metrics (which store none, to keep the
    working set in cache). ``substeps``: default :func:`jaxcart.substeps.substeps_per_sample`.
    Raises :class:`jaxcart.runcheck.IncompatibleRun` for a run that cannot be simulated.
    """
    check_run(plant, controller, experiment)
    smoothing = Smoothing() if smoothing is None else smoothing
    substeps = substeps_per_sample(plant) if substeps is None else int(substeps)
    ts = experiment.sample_time
    advance = _plant_step(plant, smoothing, ts, substeps)
    sensors, voltages = plant.stage("sensor"), plant.stage("voltage")
    dtype = jnp.result_type(experiment.signal)
    y0 = jnp.asarray(experiment.y0, dtype=dtype)
    yd0 = jnp.asarray(experiment.yd0, dtype=y0.dtype)
    effect_states = tuple(
        tuple(jnp.asarray(s, dtype=dtype) for s in e.init_state(ts)) for e in sensors + voltages
    )
    # The transmission's state (backlash: the play and its rate) rides in the carry; () for
    # every other plant, so the plain loop is unchanged.
    transmission = _transmission(plant)
    extra = () if transmission is None else transmission.init_state(ts)
    extra = tuple(jnp.asarray(x, dtype=dtype) for x in extra)
    zero = 0 * experiment.signal[0]
    pid_state = None
    if experiment.kind == "closed_loop":
        r0 = experiment.signal[0]
        y0_read = _measure(sensors, effect_states[: len(sensors)], y0 + zero, smoothing)[0]
        pid_state = pid_init(controller, r0, y0_read, xp=jnp)
    init = LoopState(y0 + zero, yd0 + zero, pid_state, effect_states, extra)
    config = StepConfig(
        controller, experiment.kind, y0, ts, smoothing, tuple(sensors), tuple(voltages), advance
    )
    return init, functools.partial(step, config)


def _measure(sensors, states, y, smoothing):
    new = []
    for effect, st in zip(sensors, states, strict=True):
        y, st = effect.smooth_measure(st, y, smoothing)
        new.append(st)
    return y, tuple(new)


def simulate_smooth(
    plant: Plant,
    controller: PID,
    experiment: Experiment,
    *,
    smoothing: Smoothing | None = None,
    substeps: int | None = None,
) -> Response:
    """Simulate one experiment with the smooth model; returns a :class:`Response`
    (:func:`jaxcart.simulate` with ``solver=Smooth(...)`` calls this).

    plant: :class:`jaxcart.Plant` (with its effects); controller: :class:`jaxcart.PID`
    (ignored for tap and open-loop experiments); experiment: :class:`jaxcart.Experiment`.
    smoothing: widths of the smoothed nonlinearities (default :class:`Smoothing`);
    ``jaxcart.EXACT_FORMS`` uses hard clip (fine without friction). substeps: sub-steps per
    sample (static; default :func:`jaxcart.substeps.substeps_per_sample`).

    Pure JAX: wrap in ``jax.jit``, ``jax.vmap`` over gains or plant parameters, ``jax.grad``.
    """
    init, step = loop(plant, controller, experiment, smoothing=smoothing, substeps=substeps)
    _, s = jax.lax.scan(step, init, experiment.signal)
    error = s.reference - s.position
    bad = ~jnp.isfinite(s.position) | (jnp.abs(s.position) > DIVERGED_POSITION)
    return Response(
        time=experiment.time.astype(s.position.dtype),
        position=s.position,
        velocity=s.velocity,
        reference=s.reference,
        error=error,
        command=s.command,
        voltage=s.voltage,
        diverged=jnp.any(bad),
        unlimited=s.unlimited,
        kind=experiment.kind,
    )
