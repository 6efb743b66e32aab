"""The loop as python-control systems (jaxcart.control_systems) against python-control's own
responses, jaxcart's simulator, closed forms and the pre-lab's poles."""

import dataclasses
import math

import control
import jax
import numpy as np
import pytest

import jaxcart as jc
from jaxcart import control_systems as cs
from jaxcart.errors import UserError
from jaxcart.exact import simulate_exact
from tuning.lab import prelab

PLANT = jc.handout_plant()  # linear: no friction, no amplifier limit
M, C, GAMMA = float(PLANT.m), float(PLANT.c), float(PLANT.gamma)
STEP = 0.05  # [m]: small enough that no command nears 6 V (v_limit is inf anyway)
#: Same loop, two implementations in float64: the ZOH matrix exponential (scipy) against
#: jaxcart's phi functions, 800 samples.
SAME_LOOP_TOL = 1e-9  # [m]
PIDS = {
    "P": jc.PID(kp=20.0),
    "PI": jc.PID(kp=30.0, ki=8.0),
    "PID-error": jc.PID(kp=40.0, kd=5.0, ki=5.0),
    "PID-measurement": jc.PID(kp=40.0, kd=2.0, ki=5.0, derivative_on="measurement"),
    "PD-unfiltered": jc.PID(kp=40.0, kd=2.0, tau=0.0),
}


@pytest.fixture(scope="module")
def simulate():
    return jax.jit(jc.simulate)


def _y_u(loop, t, r, x0=None):
    out = control.forced_response(loop, t, r, X0=0 if x0 is None else x0)
    return out.outputs[0], out.outputs[1]


@pytest.mark.parametrize("name", PIDS)
def test_discrete_loop_equals_simulator(name, simulate):
    """forced_response of the discrete closed loop from initial_state = jaxcart.simulate of the
    linear loop (a start off zero, so every state's initial value matters)."""
    pid = PIDS[name]
    exp = jc.step(STEP, horizon=0.8, y0=0.01)
    res = simulate(PLANT, pid, exp)
    loop = cs.closed_loop(PLANT, pid)
    assert loop.dt == pid.sample_time and loop.output_labels == ["y", "u"]
    t, r = np.asarray(res.time), np.asarray(exp.signal)
    y, u = _y_u(loop, t, r, cs.initial_state(loop, pid, r0=r[0], y0=0.01))
    assert np.max(np.abs(np.asarray(res.command))) < 3.0  # linear: far from 6 V
    assert np.max(np.abs(y - np.asarray(res.position))) < SAME_LOOP_TOL
    assert np.max(np.abs(u - np.asarray(res.command))) < 1e3 * SAME_LOOP_TOL  # [V]


def test_step_response_and_transfer_functions(simulate):
    """control.step_response (zero state) is the simulator's step where the first sample
    carries no derivative kick (derivative on measurement from rest), and the TF forms give
    the same loop and the same open-loop cart as the state-space forms."""
    pid = PIDS["PID-measurement"]
    res = simulate(PLANT, pid, jc.step(STEP, horizon=0.8))
    t = np.asarray(res.time)
    step = control.step_response(cs.closed_loop(PLANT, pid)["y", "r"], t)
    assert np.max(np.abs(STEP * step.outputs - np.asarray(res.position))) < SAME_LOOP_TOL

    pid = PIDS["PID-error"]
    # feedback(P C, 1) in polynomial form: its poles cluster near z = 1, where polynomial
    # coefficients lose digits (measured 2.4e-9 m), hence the looser 1e-8 m.
    from_tf = control.feedback(cs.plant_tf(PLANT, pid.sample_time) * cs.controller_tf(pid), 1)
    r = np.full(t.size, STEP)
    y_ss, _ = _y_u(cs.closed_loop(PLANT, pid), t, r)
    assert np.max(np.abs(control.forced_response(from_tf, t, r).outputs - y_ss)) < 1e-8
    # The error-path TF is the state-space PID's r -> u path, at every frequency.
    w = np.array([0.1, 3.0, 100.0, 2000.0])
    tf_resp = cs.controller_tf(pid)(np.exp(1j * w * pid.sample_time))
    ss_resp = cs.controller_ss(pid)["u", "r"](np.exp(1j * w * pid.sample_time))
    np.testing.assert_allclose(tf_resp, ss_resp, rtol=1e-8)  # 1.6e-10 near the pole z = 1

    # The ZOH cart alone against the closed form of a voltage step (exact at the samples):
    # y = (gamma V / c) (t - (m / c)(1 - exp(-c t / m))).
    volts = 2.0
    y_ref = volts * GAMMA / C * (t - M / C * (1 - np.exp(-C * t / M)))
    for sys in (cs.plant_ss(PLANT, 1e-3), cs.plant_tf(PLANT, 1e-3)):
        y = volts * control.step_response(sys, t).outputs
        assert np.max(np.abs(y - y_ref)) < SAME_LOOP_TOL


def _zoh_characteristic(pid):
    """Closed-loop characteristic polynomial from closed forms only: the ZOH cart
    K/(s (s + a)) -> K [(a T - 1 + e) z + (1 - e - a T e)] / (a^2 (z - 1)(z - e)), e = e^(-a T),
    and the PID of docs/design.md, kp + ki T/(z - 1) + kd (z - 1)/((tau + T) z - tau)."""
    T, a, k = pid.sample_time, C / M, GAMMA / M
    e = math.exp(-a * T)
    p_num = k / a**2 * np.array([a * T - 1 + e, 1 - e - a * T * e])
    p_den = np.polymul([1, -1], [1, -e])
    h = pid.tau + T
    c_num = np.polyadd(
        np.polymul([pid.kp], np.polymul([1, -1], [h, -pid.tau])),
        np.polyadd(np.polymul([pid.ki * T], [h, -pid.tau]), np.polymul([pid.kd], [1, -2, 1])),
    )
    c_den = np.polymul([1, -1], [h, -pid.tau])
    return np.polyadd(np.polymul(c_den, p_den), np.polymul(c_num, p_num))


def test_poles_against_closed_forms_and_prelab():
    pid = PIDS["PID-error"]
    poles = np.sort_complex(cs.closed_loop_poles(PLANT, pid))
    reference = np.sort_complex(np.roots(_zoh_characteristic(pid)))
    np.testing.assert_allclose(poles, reference, rtol=0, atol=1e-9)
    assert cs.is_stable(PLANT, pid)

    # Continuous PI at the Routh bound k_i = c k / m: poles at +/- j sqrt(gamma k / m), the
    # same as the pre-lab's python-control construction, and the bound separates stable loops.
    k = prelab.K_PI
    ki = prelab.ki_bound_routh(M, C, k)
    poles = np.sort_complex(cs.closed_loop_poles(PLANT, jc.PID(kp=k, ki=ki), discrete=False))
    np.testing.assert_allclose(
        poles, np.sort_complex(prelab.closed_loop_poles(M, C, GAMMA, k, ki)), atol=1e-9
    )
    assert np.min(np.abs(poles - 1j * math.sqrt(GAMMA * k / M))) < 1e-9
    assert cs.is_stable(PLANT, jc.PID(kp=k, ki=0.99 * ki), discrete=False)
    assert not cs.is_stable(PLANT, jc.PID(kp=k, ki=1.01 * ki), discrete=False)
    assert not cs.is_stable(PLANT, jc.PID(kp=-100.0))  # the kp = -100 file


@pytest.mark.parametrize("delay", [0.0, 0.0034])
def test_continuous_loop_is_the_limit_of_the_discrete_one(delay):
    """Continuous PID on the continuous cart against the discrete loop: the difference is first
    order in Ts (half a sample of hold delay and the Euler forms); at 0.1 ms it is below
    1.5e-4 of the step in position (measured 1.1e-4 and 1.2e-4 with a 3.4 ms delay, whose
    order-6 Pade approximant adds nothing visible) and 10x smaller than at 1 ms."""
    plant = jc.build_plant({"delay": delay}) if delay else PLANT
    base = PIDS["PID-error"]
    errors = []
    for ts in (1e-3, 1e-4):
        pid = dataclasses.replace(base, sample_time=ts)
        t = np.arange(int(round(0.6 / ts)) + 1) * ts
        r = np.full(t.size, STEP)
        out = []
        for loop in (cs.closed_loop(plant, pid), cs.closed_loop(plant, pid, discrete=False)):
            out.append(_y_u(loop, t, r, cs.initial_state(loop, pid, r0=STEP))[0])
        errors.append(np.max(np.abs(out[0] - out[1])))
    assert errors[1] < 1.5e-4 * STEP
    assert 8.0 < errors[0] / errors[1] < 12.0


@pytest.mark.parametrize("delay", [0.0034, 0.003])
def test_delay_is_exact_in_discrete_time(delay):
    """A delay effect (a split sample, then whole samples) in the discrete cart equals the
    exact simulator's delay line (jaxcart.exact: numpy, event-exact, no compile)."""
    plant = jc.build_plant({"delay": delay})
    pid = PIDS["PID-error"]
    exp = jc.step(STEP, horizon=0.8)
    res = simulate_exact(plant, pid, exp)
    loop = cs.closed_loop(plant, pid)
    lags = math.ceil(round(delay / pid.sample_time, 9))
    assert [x for x in loop.state_labels if x.startswith("cart_u")] == [
        f"cart_u_{j + 1}" for j in range(lags)
    ]
    t, r = np.asarray(res.time), np.asarray(exp.signal)
    y, u = _y_u(loop, t, r, cs.initial_state(loop, pid, r0=r[0]))
    assert np.max(np.abs(y - np.asarray(res.position))) < SAME_LOOP_TOL
    assert np.max(np.abs(u - np.asarray(res.command))) < 1e3 * SAME_LOOP_TOL


def test_bad_input_is_one_clear_error():
    with pytest.raises(UserError, match="tau > 0"):
        cs.controller_tf(jc.PID(kp=1.0, kd=1.0, tau=0.0), discrete=False)
    with pytest.raises(UserError, match="batch"):
        cs.plant_ss(PLANT.replace(B_eq=np.array([4.0, 5.0])))
    with pytest.raises(ValueError, match="kp = nan V/m: give a finite number"):
        jc.PID(kp=math.nan)  # the one rule of a PID setting (hw.control_law)
    with pytest.raises(UserError, match="finite"):  # an array leaf is not checked by PID
        cs.closed_loop(PLANT, jc.PID(kp=np.array(math.nan)))


@pytest.mark.parametrize("name", PIDS)
def test_poles_are_the_eigenvalues_of_the_plausibility_check(name):
    """jaxcart.plausibility builds its own 5 x 5 loop matrix (states y, y', I, d, s): its
    eigenvalues are these poles plus one per state that no gain uses (z = 0 for s_{k-1} with a
    minimal derivative, 1 for I without ki, tau/(tau + Ts) for d without kd)."""
    from jaxcart.plausibility import closed_loop_eigenvalues

    pid = PIDS[name]
    rest = list(closed_loop_eigenvalues(pid, PLANT))
    for pole in cs.closed_loop_poles(PLANT, pid):
        nearest = min(range(len(rest)), key=lambda i: abs(rest[i] - pole))
        assert abs(rest.pop(nearest) - pole) < 1e-9
    unused = [0.0] + ([1.0] if pid.ki == 0 else [])
    unused += [pid.tau / (pid.tau + pid.sample_time)] if pid.kd == 0 else []
    np.testing.assert_allclose(np.sort(np.real(rest)), np.sort(unused), atol=1e-9)
