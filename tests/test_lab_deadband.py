"""The Coulomb dead band of a P loop as the lab report states it (tuning/lab/deadband.py),
against the exact simulator (event-exact stick-slip, the 1 ms digital loop) and the encoder.

References: the rest condition k gamma |e| <= f_c; the linear loop's slow mode for the creep
of an overdamped approach; the encoder reading whole counts below the cart.
"""

import math

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.exact import simulate_exact
from jaxcart.synthetic import make_recording
from tuning.estimation.engine.noise import encoder_count
from tuning.lab import data, deadband

Q = data.TRUE["quantization"]


@pytest.fixture(scope="module")
def cart():
    """The built-in true cart without the amplifier limit (the steps below stay under 6 V)."""
    return jc.build_plant({"M": 0.94, "B_eq": 4.6, "f_c": 0.45})


def _loop(plant, k):
    return float(plant.m), float(plant.c), float(plant.gamma), k


def test_overdamped_cart_creeps_to_the_edge_as_the_slow_pole_says(cart):
    # k = 10 V/m, step 0.2 m (Part (iii)): real poles; the cart never enters the band in
    # finite time and its distance from the edge is the linear model's x(t) (tolerance 5 %:
    # the digital loop's zero-order hold against the continuous model, about 1 %).
    m, c, gamma, k = _loop(cart, 10.0)
    assert deadband.overdamped(m, c, gamma, k)
    b = deadband.band(0.45, k, gamma)
    run = simulate_exact(cart, jc.PID(kp=k), jc.step(0.2, horizon=6.0))
    e = np.asarray(run.error)
    assert np.all(e > b)  # never inside the band: the error bound holds only at t -> inf
    for t in (3.0, 4.0, 5.0, 6.0):
        x = deadband.creep(m, c, gamma, k, 0.45, 0.2, t)
        assert e[int(round(t * 1000))] - b == pytest.approx(x, rel=0.05), t
    # The stated bound for a run that ends at T: |e(T)| <= b + creep(T) (with 5 % slack on
    # the creep); and the creep itself falls as the slower pole says.
    assert e[-1] <= b + 1.05 * deadband.creep(m, c, gamma, k, 0.45, 0.2, 6.0)
    slow = max(deadband.poles(m, c, gamma, k).real)
    ratio = deadband.creep(m, c, gamma, k, 0.45, 0.2, 6.0) / deadband.creep(
        m, c, gamma, k, 0.45, 0.2, 5.0
    )
    assert ratio == pytest.approx(math.exp(slow), rel=1e-3)


def test_underdamped_cart_sticks_inside_the_band(cart):
    # k = 100 V/m: complex poles; the cart overshoots, reverses and sticks, |e| <= b exactly.
    m, c, gamma, k = _loop(cart, 100.0)
    assert not deadband.overdamped(m, c, gamma, k)
    assert deadband.creep(m, c, gamma, k, 0.45, 0.05, 3.0) == 0.0
    run = simulate_exact(cart, jc.PID(kp=k), jc.step(0.05, horizon=3.0))
    b = deadband.band(0.45, k, gamma)
    tail = np.asarray(run.position)[-500:]
    assert np.ptp(tail) == 0.0 and np.all(np.asarray(run.velocity)[-500:] == 0.0)  # stuck
    assert abs(float(run.error[-1])) <= b


def test_encoder_adds_at_most_one_count_and_the_lower_bound_holds():
    # The built-in P 10 recording (8 s): the recorded error lies in [e_true, e_true + q), so
    # it meets b + creep + q, and the lab's lower bound k gamma (|e| - q) stays below the true
    # f_c (without the count it would not: 0.4502 N > 0.45 N).
    plant = data.true_plant()
    rec = make_recording(plant, jc.PID(kp=10.0), jc.step(0.2, horizon=8.0), seed=data.SEED)
    e_true = 0.2 - rec.true_position[-1]  # the reference is in the encoder frame
    e_meas = 0.2 - rec.position[-1]
    assert 0.0 <= e_meas - e_true < Q
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    b = deadband.band(0.45, 10.0, gamma)
    creep = deadband.creep(m, c, gamma, 10.0, 0.45, 0.2, 8.0)
    assert encoder_count(rec.position) == pytest.approx(Q, rel=1e-9)
    assert abs(e_meas) <= b + creep + Q
    lower = deadband.f_c_lower(e_meas, 10.0, gamma, Q)
    assert 0.449 < lower <= 0.45
    assert 10.0 * gamma * abs(e_meas) > 0.45  # the uncorrected bound overshoots the truth
