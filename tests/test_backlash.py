"""Backlash (jaxcart.effects.backlash) in both simulators: no play is the plain plant, the dwell
after a start or a reversal against the free motor's closed form with the momentum shared at
impact, smooth -> exact, the gradient in the play, and plants that combine it with friction and
saturation."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

import jaxcart as jc
from jaxcart.exact import simulate_exact
from jaxcart.plantspec import build_plant

PID_STEP = jc.PID(kp=40.0, kd=3.0, ki=5.0, v_limit=6.0)
STEP = jc.step(0.3, horizon=0.6)
SUBSTEPS = 4


def _phis(a, t):
    """e^{-a t}, (1 - e^{-a t})/a [s], (t - phi1)/a [s^2] (a > 0): the closed forms of
    y'' = -a y' + b, written here independently of both simulators."""
    e = math.exp(-a * t)
    phi1 = (1.0 - e) / a
    return e, phi1, (t - phi1) / a


@pytest.mark.parametrize("values", [{}, {"f_c": 0.3, "v_sat": 5.0}])
def test_no_play_is_the_plant_without_backlash(values):
    plain = build_plant(values)
    play = build_plant({**values, "backlash": 0.0})
    ex = simulate_exact(play, PID_STEP, STEP).position
    np.testing.assert_allclose(ex, simulate_exact(plain, PID_STEP, STEP).position, atol=1e-9)
    sm = jc.simulate(play, PID_STEP, STEP, substeps=SUBSTEPS).position
    ref = jc.simulate(plain, PID_STEP, STEP, substeps=SUBSTEPS).position
    np.testing.assert_allclose(np.asarray(sm), np.asarray(ref), atol=1e-9)


def _both(plant, exp):
    ex = simulate_exact(plant, None, exp)
    sm = jc.simulate(plant, None, exp, smoothing=jc.EXACT_FORMS, substeps=SUBSTEPS)
    return ex, sm


def test_start_dwell_and_momentum_at_impact():
    """From rest mid-gap under a voltage step V: the cart stays exactly put until the motor,
    free (M_J x'' = gamma V - B_emf x'), has crossed b/2; then it jumps to M_J x'(t*)/m and
    moves as the joined plant."""
    b, volts = 5e-4, 2.0
    plant = build_plant({"backlash": b})
    exp = jc.voltage_step(volts, horizon=0.05)
    m_j, m, c, g = float(plant.M_J), float(plant.m), float(plant.c), float(plant.gamma)
    a_m, acc = float(plant.B_emf) / m_j, g * volts / m_j
    t_star = brentq(lambda t: _phis(a_m, t)[2] * acc - b / 2, 1e-9, 0.05)
    v0 = m_j * _phis(a_m, t_star)[1] * acc / m  # inelastic: the motor's momentum shared
    t = np.asarray(exp.time)
    after = t > t_star
    expected = np.zeros_like(t)
    for k in np.nonzero(after)[0]:
        _, phi1, phi2 = _phis(c / m, t[k] - t_star)
        expected[k] = phi1 * v0 + phi2 * g * volts / m
    assert 2 < np.count_nonzero(~after) < 20  # the dwell spans several samples
    ex, sm = _both(plant, exp)
    assert np.all(ex.position[~after] == 0.0)
    np.testing.assert_allclose(ex.position, expected, atol=1e-10)
    np.testing.assert_allclose(np.asarray(sm.position), expected, atol=1e-8)


def test_reversal_coasts_until_the_gap_is_crossed():
    """After the drive reverses from +V to -V the pinion leaves the rack at once: the cart
    coasts on its own (M y'' = -B_eq y') while the motor crosses the play b from its contact."""
    b, volts, k_r = 3e-4, 2.0, 200
    plant = build_plant({"backlash": b})
    u = np.where(np.arange(401) < k_r, volts, -volts)
    exp = jc.voltage_sequence(u)
    ex, sm = _both(plant, exp)
    y_r, v_r = float(ex.position[k_r]), float(ex.velocity[k_r])
    m_j, big_m, g = float(plant.M_J), float(plant.M), float(plant.gamma)
    a_m, a_c, acc = float(plant.B_emf) / m_j, float(plant.B_eq) / big_m, -g * volts / m_j

    def play(t):  # d(t) - (-b/2): the gap left to cross
        _, p1m, p2m = _phis(a_m, t)
        return b + (p1m * v_r + p2m * acc) - _phis(a_c, t)[1] * v_r

    t_star = brentq(play, 1e-9, 0.05)
    t = np.asarray(exp.time) - k_r * 1e-3
    coast = (t >= 0) & (t < t_star)
    expected = np.array([y_r + _phis(a_c, tk)[1] * v_r for tk in t[coast]])
    assert np.count_nonzero(coast) >= 3
    np.testing.assert_allclose(ex.position[coast], expected, atol=1e-10)
    np.testing.assert_allclose(np.asarray(sm.position)[coast], expected, atol=1e-8)
    # After the impact the drive acts again: the cart leaves the coasting curve.
    k_hit = np.nonzero(t > t_star)[0][1]
    coasting = y_r + _phis(a_c, t[k_hit])[1] * v_r
    assert coasting - ex.position[k_hit] > 1e-6


def test_smooth_converges_to_exact_with_friction_and_saturation():
    plant = build_plant({"backlash": 2e-4, "f_c": 0.3, "v_sat": 5.0})
    ref = simulate_exact(plant, PID_STEP, STEP)
    assert not ref.diverged
    errors = []
    for scale in (1.0, 0.001):
        sm = jc.simulate(
            plant, PID_STEP, STEP, smoothing=jc.Smoothing().scaled(scale), substeps=SUBSTEPS
        )
        errors.append(float(np.max(np.abs(np.asarray(sm.position) - ref.position))))
    assert errors[0] / errors[1] >= 10 and errors[1] < 1e-8, errors
    # The play matters: far above that error.
    plain = simulate_exact(build_plant({"f_c": 0.3, "v_sat": 5.0}), PID_STEP, STEP)
    assert np.max(np.abs(plain.position - ref.position)) > 1e-5


def test_gradient_in_the_play_matches_central_differences():
    # Without friction: its linearization inside the sub-step loop quadruples the compile time
    # (with f_c = 0.3 the derivative also matches: -0.0652893 vs -0.0652894, measured).
    plant = build_plant({"backlash": 2e-4, "v_sat": 5.0})
    exp = jc.step(0.3, horizon=0.3)  # the overshoot and its reversal are within 0.3 s
    w = jnp.linspace(0.0, 1.0, exp.n_samples)

    @jax.jit
    def loss(b):
        res = jc.simulate(plant.replace(backlash=b), PID_STEP, exp)
        return jnp.sum(w * res.position) / exp.n_samples

    b0 = jnp.asarray(2e-4)
    # Forward mode: the same derivative as grad, and it compiles in a fraction of the time
    # (reverse mode through the sub-step loop is covered by the contract test).
    g = jax.jvp(loss, (b0,), (jnp.ones_like(b0),))[1]
    h = 1e-9
    fd = (loss(b0 + h) - loss(b0 - h)) / (2 * h)
    assert float(g) == pytest.approx(float(fd), rel=2e-3)
    assert abs(float(g)) > 1e-3  # the play moves the run
