"""The exact simulator against closed-form solutions, the Routh bound, the friction band, and the
smooth simulator's limit as its widths go to 0."""

import dataclasses
import math

import jax
import numpy as np
import pytest
import scipy.linalg

from jaxcart import (
    EXACT_FORMS,
    PID,
    Coulomb,
    Effect,
    Plant,
    Saturation,
    Smoothing,
    handout_plant,
    setpoints,
    simulate,
    step,
    step_info,
    tap,
    tap_plant,
    voltage_sequence,
    voltage_step,
)
from jaxcart.exact import simulate_exact, step_info_exact, voltage_limit
from jaxcart.smooth_sim import DIVERGED_POSITION

#: Closed-form solutions vs the simulator: both exact, so only rounding separates them [m].
CLOSED_FORM_TOL = 1e-10
F_C = 1.0  # Coulomb friction of the friction tests [N]


def _slip(t, y0, v0, a, b):
    """Independent reference: y(t) of y'' = -a y' + b (a > 0), written with plain exp."""
    return y0 + (b / a) * t + (v0 - b / a) * (1.0 - np.exp(-a * t)) / a


# ---------------------------------------------------------------- 1. open-loop voltage step


@pytest.mark.parametrize("f_c", [0.0, F_C])
def test_voltage_step_matches_closed_form(f_c):
    """y(t) = (F/c)(t - (m/c)(1 - e^{-ct/m})), F = gamma V - f_c while slipping forward."""
    plant = handout_plant(f_c=f_c)  # 6 V saturation, not reached by 3 V
    volts = 3.0
    res = simulate_exact(plant, None, voltage_step(volts, horizon=1.0))
    m, c = float(plant.m), float(plant.c)
    force = float(plant.gamma) * volts - f_c
    t = res.time
    y = (force / c) * (t - (m / c) * (1.0 - np.exp(-c * t / m)))
    yd = (force / c) * (1.0 - np.exp(-c * t / m))
    np.testing.assert_allclose(res.position, y, rtol=0, atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(res.velocity, yd, rtol=0, atol=CLOSED_FORM_TOL)
    np.testing.assert_array_equal(res.voltage, volts)
    np.testing.assert_array_equal(res.error, res.reference - res.position)
    assert res.kind == "open_loop" and not res.diverged


def test_zero_damping_is_exact():
    """c = 0 (motor unplugged, B_eq = 0): y = v0 t - f t^2/(2m) until t_stop = m v0/f; and a
    tiny c gives the same to first order in c (the series branch, no cancellation)."""
    v0 = 0.4
    plant = tap_plant(B_eq=0.0, effects=(Coulomb(f_c=F_C),))
    res = simulate_exact(plant, None, tap(v0, horizon=1.0))
    m = float(plant.m)
    t_stop = m * v0 / F_C
    t = np.minimum(res.time, t_stop)
    np.testing.assert_allclose(
        res.position, v0 * t - F_C * t**2 / (2 * m), rtol=0, atol=CLOSED_FORM_TOL
    )
    assert np.all(res.velocity[res.time > t_stop] == 0.0)
    tiny = simulate_exact(dataclasses.replace(plant, B_eq=1e-9), None, tap(v0, horizon=1.0))
    # The first-order effect of c = 1e-9 kg/s over 1 s is ~1e-10 m.
    np.testing.assert_allclose(tiny.position, res.position, rtol=0, atol=1e-9)


#: Two exact simulators, rounding accumulated differently over 1000 samples (measured <= 3e-13 m,
#: 1e-12 m/s, 2e-11 V; the voltage carries the derivative gain kd/(tau + Ts) ~ 450 V/m).
AGREEMENT_TOL = {
    "position": 1e-11,
    "error": 1e-11,
    "velocity": 1e-11,
    "command": 1e-9,
    "voltage": 1e-9,
}


def test_matches_exact_forms_of_smooth_simulator_without_friction():
    """Without friction both simulators are exact (hard clip, exact ZOH discretization), so they
    agree to rounding, for every controller option."""
    plant = handout_plant()
    exp = step(0.5, horizon=1.0)
    for pid in (
        PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0),
        PID(kp=40.0, kd=5.0, ki=30.0, v_limit=5.0, anti_windup="clamping"),
        PID(kp=40.0, kd=5.0, ki=30.0, v_limit=6.0, anti_windup="back_calculation", kb=3.0),
        PID(kp=30.0, kd=4.0, ki=5.0, tau=0.0, derivative_on="measurement"),
    ):
        exact = simulate_exact(plant, pid, exp)
        smooth = simulate(plant, pid, exp, smoothing=EXACT_FORMS)
        for name, tol in AGREEMENT_TOL.items():
            np.testing.assert_allclose(
                getattr(exact, name),
                np.asarray(getattr(smooth, name)),
                rtol=0,
                atol=tol,
                err_msg=f"{name} with {pid}",
            )


# ---------------------------------------------------------------- 2. sticking


def test_cart_at_rest_within_friction_stays_exactly_at_rest():
    """|gamma u| < f_c at every sample: velocity exactly 0, position exactly y0 (no chatter)."""
    plant = handout_plant(f_c=F_C)
    u_max = 0.99 * F_C / float(plant.gamma)
    u = u_max * np.sin(np.arange(500) * 0.05)  # changes sign, never breaks away
    res = simulate_exact(plant, None, voltage_sequence(u, y0=0.2))
    assert np.all(res.velocity == 0.0)
    assert np.all(res.position == 0.2)


@pytest.mark.parametrize(
    "plant",
    [tap_plant(effects=(Coulomb(f_c=F_C),)), handout_plant(f_c=F_C)],
    ids=["tap", "motor_connected"],
)
def test_coasting_cart_stops_at_closed_form_time_and_position(plant):
    """From v0 with no drive: t_stop = (m/c) ln(1 + c v0/f_c), y_stop = (m v0 - f_c t_stop)/c;
    slip before, stopped (velocity exactly 0, position constant) after."""
    v0, y0 = 0.5, -0.1
    exp = voltage_sequence(np.zeros(1001), y0=y0, yd0=v0)  # open loop at 0 V
    res = simulate_exact(plant, None, exp)
    m, c = float(plant.m), float(plant.c)
    t_stop = (m / c) * math.log(1.0 + c * v0 / F_C)
    y_stop = y0 + (m * v0 - F_C * t_stop) / c
    moving = res.time < t_stop
    assert 10 < moving.sum() < res.time.size - 10  # the stop lies inside the run
    np.testing.assert_allclose(
        res.position[moving],
        _slip(res.time[moving], y0, v0, c / m, -F_C / m),
        rtol=0,
        atol=CLOSED_FORM_TOL,
    )
    assert np.all(res.velocity[moving] > 0)
    np.testing.assert_allclose(res.position[~moving], y_stop, rtol=0, atol=CLOSED_FORM_TOL)
    assert np.all(res.velocity[~moving] == 0.0)
    assert np.all(res.position[~moving] == res.position[-1])


def test_reversal_inside_a_sample():
    """Moving backwards against a drive beyond f_c: stops at t1 (closed form) and slips forward,
    events inside samples, piecewise closed form throughout."""
    plant = handout_plant(f_c=F_C)
    volts, v0 = 2.0, -0.3
    res = simulate_exact(plant, None, voltage_sequence(np.full(400, volts), yd0=v0))
    m, c, force = float(plant.m), float(plant.c), float(plant.gamma) * volts
    a, b1, b2 = c / m, (force + F_C) / m, (force - F_C) / m
    t1 = math.log(1.0 - a * v0 / b1) / a
    y1 = _slip(t1, 0.0, v0, a, b1)
    t = res.time
    expected = np.where(t < t1, _slip(t, 0.0, v0, a, b1), _slip(t - t1, y1, 0.0, a, b2))
    assert 0.01 < t1 < 0.3 and (t1 / 1e-3) % 1 > 1e-3  # a genuine event inside a sample
    np.testing.assert_allclose(res.position, expected, rtol=0, atol=CLOSED_FORM_TOL)


def test_stop_at_a_sample_boundary_never_reverses():
    """v0 chosen so that the cart stops exactly at t = Ts (v0 = (f_c - F)/c (e^{c Ts/m} - 1)),
    perturbed by a few ulps either side: rounding must never leave a reversed velocity (measured:
    without the sign guard 8 of these 4221 runs end the sample with y' ~ -1e-17 m/s)."""
    plant = handout_plant(f_c=F_C)
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    reversed_runs = []
    for volts in np.linspace(-0.5, 0.5, 21):  # |gamma V| < f_c: decelerates, then sticks
        v0 = (F_C - gamma * volts) / c * math.expm1(c / m * 1e-3)
        for j in range(-100, 101):
            exp = voltage_sequence(np.full(3, volts), yd0=v0 * (1 + j * 1.1e-16))
            res = simulate_exact(plant, None, exp)
            if np.any(res.velocity < 0) or res.velocity[-1] != 0.0:
                reversed_runs.append((volts, j))
    assert not reversed_runs


# ---------------------------------------------------------------- 3. smooth -> exact


FACTORS = (1.0, 0.3, 0.1, 0.03)
SUBSTEPS = 50  # integration error of the smooth simulator well below its smoothing error


@pytest.fixture(scope="module")
def smooth_sim():
    return jax.jit(lambda p, c, e, s: simulate(p, c, e, smoothing=s, substeps=SUBSTEPS))


CONVERGENCE_CASES = {
    # name: (plant, controller, experiment, bound on the max error at the smallest width [m])
    "saturation_pid": (
        handout_plant(),
        PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0),
        step(0.5, horizon=2.0),
        1e-4,
    ),
    "coulomb_p": (
        handout_plant(f_c=F_C),
        PID(kp=20.0, v_limit=6.0),
        step(0.5, horizon=2.0),
        1e-4,
    ),
    "coulomb_tap": (tap_plant(effects=(Coulomb(f_c=F_C),)), None, tap(0.5, horizon=1.0), 1e-7),
}


@pytest.mark.parametrize("name", list(CONVERGENCE_CASES))
def test_smooth_simulator_converges_to_exact(smooth_sim, name):
    """Max position error of the smooth simulator vs the exact one, widths scaled by FACTORS:
    shrinks >= 10x from the largest to the smallest width and ends below the case's bound."""
    plant, pid, exp, bound = CONVERGENCE_CASES[name]
    exact = simulate_exact(plant, pid, exp)
    pid = PID() if pid is None else pid
    errors = [
        float(
            np.max(
                np.abs(
                    np.asarray(smooth_sim(plant, pid, exp, Smoothing().scaled(f)).position)
                    - exact.position
                )
            )
        )
        for f in FACTORS
    ]
    table = ", ".join(f"{f:g}: {e:.3g} m" for f, e in zip(FACTORS, errors, strict=True))
    assert errors[0] >= 10 * errors[-1], table
    assert errors[-1] < bound, table


# ---------------------------------------------------------------- 4. P control with friction


@pytest.mark.parametrize("kp", [40.0, 60.0, 100.0])
def test_p_control_sticks_inside_friction_band(kp):
    """P control with Coulomb friction: the cart sticks (velocity exactly 0, position constant)
    with |e| <= f_c / (k gamma), the Coulomb dead band of docs/design.md, "The physics"
    (rounding allowance 1e-12 relative)."""
    plant = handout_plant(f_c=F_C)
    res = simulate_exact(plant, PID(kp=kp, v_limit=6.0), step(0.5, horizon=2.0))
    band = F_C / (kp * float(plant.gamma))
    tail = slice(-500, None)
    assert np.all(res.velocity[tail] == 0.0)
    assert np.all(res.position[tail] == res.position[-1])
    assert abs(res.error[-1]) <= band * (1 + 1e-12)
    if kp == 40.0:
        # Measured 0.65 of the band: the cart stops where its velocity reaches 0, not at the edge.
        assert abs(res.error[-1]) < 0.8 * band


def test_overdamped_p_control_creeps_to_the_band_edge():
    """k = 20 V/m: the linear approach is overdamped (c^2 > 4 m k gamma), so the cart slides
    towards the band edge e = f_c/(k gamma) from outside and gets there only as t -> inf."""
    plant = handout_plant(f_c=F_C)
    kp = 20.0
    assert float(plant.c) ** 2 > 4 * float(plant.m) * kp * float(plant.gamma)
    res = simulate_exact(plant, PID(kp=kp, v_limit=6.0), step(0.5, horizon=8.0))
    band = F_C / (kp * float(plant.gamma))
    np.testing.assert_allclose(res.error[-1], band, rtol=1e-8)


# ---------------------------------------------------------------- 5. the PI bound k_i < c k / m


def _discrete_growth_rate(plant, kp, ki, ts):
    """Independent reference: log of the spectral radius / Ts of the sampled PI loop, from the
    matrix-exponential ZOH discretization (scipy) [1/s]."""
    m, c, g = float(plant.m), float(plant.c), float(plant.gamma)
    cont = np.array([[0.0, 1.0, 0.0], [0.0, -c / m, g / m], [0.0, 0.0, 0.0]])
    zoh = scipy.linalg.expm(cont * ts)
    ad, bd = zoh[:2, :2], zoh[:2, 2:]
    loop = np.zeros((3, 3))  # state (y, y', I); u = -kp y + ki I; I += Ts (-y)
    loop[:2, :2] = ad + bd @ np.array([[-kp, 0.0]])
    loop[:2, 2:] = bd * ki
    loop[2] = [-ts, 0.0, 1.0]
    return math.log(max(abs(np.linalg.eigvals(loop)))) / ts


@pytest.mark.parametrize("fraction", [0.8, 1.25])
def test_pi_stability_bound(fraction):
    """PI, k = 10 V/m, no saturation, B_eq = 5.4: stable below k_i = c k/m (122.3 V/(m s)),
    unstable above. The 1 ms loop moves the bound to 0.987 of Routh's, so 0.8x and 1.25x keep
    margins of 19 % and 27 %. Envelope growth over 10 s vs the sampled loop's eigenvalues."""
    plant = Plant(effects=())
    kp = 10.0
    ki = fraction * float(plant.c) * kp / float(plant.m)
    res = simulate_exact(plant, PID(kp=kp, ki=ki, kd=0.0), step(0.01, horizon=20.0))
    t, e = res.time, np.abs(res.error)
    early = e[(t >= 8.0) & (t < 10.0)].max()  # 2 s windows span more than a period (1.6 s)
    late = e[(t >= 18.0) & (t < 20.0)].max()
    rate = math.log(late / early) / 10.0
    expected = _discrete_growth_rate(plant, kp, ki, 1e-3)
    if fraction < 1:
        assert late < 0.5 * early
    else:
        assert late > 2.0 * early
    # Envelope read from samples of a 4 rad/s oscillation: 0.01 1/s covers peak sampling.
    assert rate == pytest.approx(expected, abs=0.01)


# ---------------------------------------------------------------- divergence, metrics, bad input


def test_divergence_stops_and_fills_nan():
    plant = Plant(effects=())
    res = simulate_exact(plant, PID(kp=-2000.0), step(0.5, horizon=3.0))  # positive feedback
    assert res.diverged
    bad = np.nonzero(~(np.abs(res.position) <= DIVERGED_POSITION))[0]
    first = bad[0]
    assert abs(res.position[first]) > DIVERGED_POSITION
    assert np.all(np.isnan(res.position[first + 1 :]))
    assert np.all(np.isfinite(res.position[:first]))
    assert step_info_exact(plant, PID(kp=-2000.0), step(0.5, horizon=3.0)).diverged


def test_step_info_exact_uses_the_smaller_voltage_limit():
    plant = handout_plant(f_c=F_C, v_sat=6.0)
    pid = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=5.0)
    exp = step(0.5, horizon=2.0)
    assert voltage_limit(plant, pid) == 5.0
    assert voltage_limit(plant, dataclasses.replace(pid, v_limit=math.inf)) == 6.0
    info = step_info_exact(plant, pid, exp)
    assert info == step_info(simulate_exact(plant, pid, exp), v_limit=5.0)
    assert info.peak_voltage == 5.0 and info.saturation_time > 0


@dataclasses.dataclass(frozen=True)
class _Magnet(Effect):
    """An effect with only a smooth form (not registered: a test double)."""

    k_m: float = 1.0
    name = "magnet"
    stage = "force"

    def smooth_force(self, y, yd, v, smoothing, plant):
        return -self.k_m * y


def test_an_effect_without_an_exact_form_is_named():
    # Which effects the exact simulator supports comes from the effects themselves.
    plant = Plant(effects=(Saturation(), _Magnet()))
    with pytest.raises(NotImplementedError, match="magnet.*has no exact form"):
        simulate_exact(plant, PID(kp=10.0), step(0.1, horizon=0.1))


# ---------------------------------------------------------------- forces linear in the velocity

VELOCITY_CASES = {
    # name: (plant values, controller, experiment): a current limit that acts, with friction,
    # stiction, a voltage limit, a delay; closed loop and open loop.
    "limit_p": ({"i_max": 0.9}, PID(kp=50.0, v_limit=6.0), step(0.4, horizon=1.5)),
    "limit_coulomb": (
        {"i_max": 0.9, "f_c": 0.4},
        PID(kp=50.0, v_limit=6.0),
        step(0.4, horizon=1.5),
    ),
    "limit_stiction_pi": (
        {"i_max": 1.2, "f_c": 0.4, "f_s": 0.6},
        PID(kp=30.0, ki=15.0),
        step(0.3, horizon=2.0),
    ),
    "limit_saturation_pd": (
        {"i_max": 0.5, "f_c": 0.3, "v_sat": 5.0},
        PID(kp=80.0, kd=3.0),
        step(0.3, horizon=1.5),
    ),
    "limit_delay": (
        {"i_max": 0.7, "f_c": 0.2, "delay": 0.0025},
        PID(kp=40.0, kd=1.0),
        step(0.2, horizon=1.0),
    ),
    "limit_open_loop": ({"i_max": 0.6, "f_c": 0.3}, None, voltage_step(-5.0, horizon=0.5)),
    # A friction curve (nine breaks) beside the current limit, both ways under PID with
    # stiction: out 0.3 m, back to -0.1 m.
    "curve_limit_stiction": (
        {
            "i_max": 1.0,
            "f_c": 0.4,
            "f_s": 0.6,
            "f_curve_right": [-0.2, 0.1, 0.3],
            "f_curve_left": [0.2, 0.3, 0.1],
        },
        PID(kp=40.0, ki=10.0, kd=2.0, v_limit=6.0),
        setpoints([0.0, 0.8], [0.3, -0.1], horizon=1.6),
    ),
}
#: (position [m], velocity [m/s]) tolerances where the RK4 reference is the looser: it steps
#: over the curve's kinks at +-5, 20, 80 and 320 mm/s without locating them (measured 6.2e-10
#: m, and 8e-12 m at four times the sub-steps: it converges to the closed form).
VELOCITY_TOLERANCES = {"curve_limit_stiction": (2e-9, 2e-7)}


@pytest.mark.parametrize("name", list(VELOCITY_CASES))
def test_velocity_piecewise_closed_form_matches_rk4(name, monkeypatch):
    """A current limit's force (and a friction curve's) is piecewise linear in the velocity:
    the exact simulator solves it in closed form (jaxcart.exact._VelocityCart), events
    included. Against the RK4 cart on Ts/20 sub-steps with bisected stick-slip events (the
    effects' laws hidden from the simulator), on runs where the limit acts (it moves the cart
    by > 1 cm): 1e-11 m (measured under 1e-14 m)."""
    from jaxcart.effects import REGISTRY
    from jaxcart.plantspec import build_plant

    values, pid, exp = VELOCITY_CASES[name]
    plant = build_plant(values)
    closed = simulate_exact(plant, pid, exp)
    unlimited = simulate_exact(
        build_plant({k: v for k, v in values.items() if k != "i_max"}), pid, exp
    )
    assert np.max(np.abs(closed.position - unlimited.position)) > 0.01
    for cls in REGISTRY.values():
        if hasattr(cls, "exact_velocity_pieces") and cls.name in plant.structure:
            monkeypatch.delattr(cls, "exact_velocity_pieces")
    # The reference at Ts/20: it steps over the friction curve's kinks (1.5e-8 m at Ts/5).
    monkeypatch.setattr("jaxcart.substeps.RK4_SUBSTEPS", 20)
    rk4 = simulate_exact(plant, pid, exp)
    atol_y, atol_v = VELOCITY_TOLERANCES.get(name, (1e-11, 1e-9))
    np.testing.assert_allclose(closed.position, rk4.position, rtol=0, atol=atol_y)
    np.testing.assert_allclose(closed.velocity, rk4.velocity, rtol=0, atol=atol_v)


def test_velocity_pieces_are_the_exact_force():
    """Each effect's velocity pieces (breaks, (f0, k)) give its exact force at every velocity
    and voltage tried, to rounding (1e-12 N)."""
    from jaxcart.effects import REGISTRY
    from jaxcart.exact import _Drive

    drive = _Drive(1.76, 2.6, 7.04)
    for cls in REGISTRY.values():
        if not hasattr(cls, "exact_velocity_pieces"):
            continue
        effect = cls(**{p.name: (0.1, -0.2, 0.3) if p.size else p.start for p in cls.params})
        for v in (-6.0, -1.0, 0.0, 0.5, 6.0):
            breaks, pieces = effect.exact_velocity_pieces(drive, v)
            assert list(breaks) == sorted(breaks) and len(pieces) == len(breaks) + 1
            for yd in np.linspace(-3.0, 3.0, 121):
                f0, k = pieces[int(np.searchsorted(breaks, yd, side="right"))]
                assert f0 + k * yd == pytest.approx(
                    effect.exact_force(0.0, yd, v, drive), abs=1e-12
                )


AFFINE_CASES = {
    # name: (plant values, controller, experiment): a spring with friction, stiction (stick-slip
    # events inside samples), a delay (two pieces a sample), closed and open loop.
    "spring_p": ({"k_s": 20.0, "y_rest": 0.05, "f_c": 0.45}, PID(kp=50.0), step(0.3, horizon=1.5)),
    "spring_stiction_pi": (
        {"k_s": 5.0, "f_c": 0.4, "f_s": 0.6},
        PID(kp=30.0, ki=60.0, v_limit=6.0, anti_windup="clamping"),
        step(0.3, horizon=2.0),
    ),
    "spring_delay_pd": (
        {"k_s": 8.0, "f_c": 0.3, "delay": 0.0013},
        PID(kp=80.0, kd=3.0),
        step(0.3, horizon=1.5),
    ),
    "spring_alone_open_loop": ({"k_s": 3.0, "y_rest": -0.1}, None, voltage_step(1.5)),
    "spring_tap": ({"k_s": 20.0, "f_c": 0.45}, None, tap(0.4, horizon=1.0)),
}


@pytest.mark.parametrize("name", list(AFFINE_CASES))
def test_affine_force_map_matches_rk4(name, monkeypatch):
    """A spring's force is affine in (y, y'): the exact simulator steps each piece of a sample
    without an event in one affine map (jaxcart.exact._rk4_map), the RK4 sub-steps composed.
    Against the sub-steps themselves (the effect's affine form hidden): 1e-11 m (measured
    under 1e-12 m), and the runs have stick-slip events for the sub-steps to locate."""
    from jaxcart.effects import REGISTRY
    from jaxcart.plantspec import build_plant

    values, pid, exp = AFFINE_CASES[name]
    if exp.kind == "tap":
        plant = tap_plant(**values)
    else:
        plant = build_plant(values)
    mapped = simulate_exact(plant, pid, exp)
    monkeypatch.setattr(REGISTRY["spring"], "exact_affine", lambda self, drive: None)
    rk4 = simulate_exact(plant, pid, exp)
    np.testing.assert_allclose(mapped.position, rk4.position, rtol=0, atol=1e-11)
    np.testing.assert_allclose(mapped.velocity, rk4.velocity, rtol=0, atol=1e-9)
    if "f_c" in values:  # the cart stopped or turned: the sub-steps located events
        assert np.any(np.diff(np.sign(rk4.velocity[1:])) != 0)


def test_affine_forms_are_the_exact_force():
    """Each effect's affine form (k_y, k_yd, f0) gives its exact force at every position,
    velocity and voltage tried, to rounding (1e-12 N)."""
    from jaxcart.effects import REGISTRY
    from jaxcart.exact import _Drive

    drive = _Drive(1.76, 2.6, 7.04)
    found = 0
    for cls in REGISTRY.values():
        effect = cls(**{p.name: (0.1, -0.2, 0.3) if p.size else p.start for p in cls.params})
        affine = effect.exact_affine(drive)
        if affine is None:
            continue
        found += 1
        k_y, k_yd, f0 = affine
        for y, yd, v in zip(
            np.linspace(-0.5, 0.5, 7), np.linspace(-2, 2, 7), (-6, 0, 3) * 3, strict=False
        ):
            assert k_y * y + k_yd * yd + f0 == pytest.approx(
                effect.exact_force(y, yd, v, drive), abs=1e-12
            )
    assert found >= 1


def test_a_spring_that_oscillates_within_a_sample_keeps_the_sub_steps():
    """The affine map checks the velocity at a piece's end only: a phase whose half damped
    period is within two samples could stop and reverse unseen, so it keeps the RK4 sub-steps
    (whose checks are Ts/5 apart)."""
    from jaxcart.effects import Spring
    from jaxcart.exact import _affine_phase, _Drive

    drive = _Drive(1.76, 2.6, 7.04)
    m, c, h = 1.0, 7.0, 0.002
    assert _affine_phase(m, c, drive, [Spring(k_s=100.0)], h) is not None
    stiff = (math.pi / (2 * h)) ** 2 * m * 1.01  # pi / w just under 2 h
    assert _affine_phase(m, c, drive, [Spring(k_s=stiff)], h) is None
