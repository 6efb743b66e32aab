"""Smooth metric surrogates (jaxcart/surrogates.py) converge to the exact step_info as the width
goes to 0, on exact-simulator responses and on the lab's real recording, and have useful
gradients through the smooth simulator."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.exact import simulate_exact
from jaxcart.metrics import step_info
from jaxcart.surrogates import (
    overshoot,
    rise_time,
    settling_time,
    smooth_step,
    smooth_step_info,
    soft_max,
    steady_state_error,
)

TS = 1e-3
#: (kp, kd, ki): overshoot and a slow return; overdamped; near-optimal (peak near the band
#: edge); integral overshoot that settles; slow P-like response.
GAINS = [(60.0, 2.0, 0.0), (40.0, 5.0, 0.0), (100.0, 8.0, 0.0), (150.0, 8.0, 5.0), (20.0, 2.0, 0.0)]


@pytest.fixture(scope="module")
def responses():
    plant = jc.handout_plant()
    exp = jc.step(0.5, horizon=3.0)
    out = []
    for kp, kd, ki in GAINS:
        res = simulate_exact(plant, jc.PID(kp=kp, kd=kd, ki=ki, v_limit=6.0), exp)
        out.append(res)
    # One with friction (stick-slip: the cart stops short of the reference).
    pid = jc.PID(kp=60.0, kd=3.0, v_limit=6.0)
    out.append(simulate_exact(jc.handout_plant(f_c=0.8), pid, exp))
    return out


def _normalized(res):
    y = np.asarray(res.position, dtype=float)
    return (y - y[0]) / (float(res.reference[-1]) - y[0])


def _slope(res, t):
    """Mean |dz/dt| [1/s] of the normalized response z = (y - y0) / A over +/-3 samples of t."""
    z = _normalized(res)
    k = int(round(t / TS))
    return float(np.mean(np.abs(np.diff(z[max(k - 3, 0) : k + 4])))) / TS


def _check_convergence(res):
    exact = step_info(res)
    assert np.isfinite(exact.settling_time), "pick responses that settle"
    t10 = float(np.asarray(res.time)[np.argmax(_normalized(res) >= 0.1)])
    amplitude = abs(float(res.reference[-1] - res.position[0]))
    errors = []
    for width in (1e-3, 1e-4, 1e-5):
        s = smooth_step_info(res, width=width)
        # Tolerances: a crossing is smeared over the time the response takes to move 2 widths
        # (the smooth step's support), plus one sample; overshoot within 100 * width % (soft max
        # below the max by ~width/2, smooth relu above by width/2); steady-state error within
        # width * |A| (and never below the exact one).
        settle_tol = TS + 2 * width / _slope(res, exact.settling_time - TS)
        rise_tol = (
            TS + 2 * width / _slope(res, t10) + 2 * width / _slope(res, t10 + exact.rise_time)
        )
        assert abs(float(s.settling_time) - exact.settling_time) <= settle_tol, width
        assert abs(float(s.rise_time) - exact.rise_time) <= rise_tol, width
        assert abs(float(s.overshoot) - exact.overshoot) <= 100 * width, width
        assert 0 <= float(s.steady_state_error) - exact.steady_state_error <= width * amplitude
        errors.append(abs(float(s.settling_time) - exact.settling_time))
    # At the smallest width the surrogate is the exact metric to one sample.
    assert errors[-1] <= TS + 1e-12


@pytest.mark.parametrize("index", range(len(GAINS) + 1))
def test_converges_to_step_info_on_exact_responses(responses, index):
    _check_convergence(responses[index])


def test_converges_on_the_real_recording(realdata):
    from jaxcart.files import read_experiment

    res = read_experiment(os.path.join(realdata, "p50.toml")).as_response()
    _check_convergence(res)


def test_surrogate_is_finite_where_the_run_does_not_settle(responses):
    # kp 40, kd 5, ki 5: the integral creep leaves the band at the end of 3 s (exact: inf).
    res = simulate_exact(
        jc.handout_plant(), jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0), jc.step(0.5, horizon=3.0)
    )
    assert step_info(res).settling_time == np.inf
    s = float(settling_time(res.time, res.position, res.reference, width=1e-3))
    assert s == pytest.approx(3.0 + TS, abs=1e-9)


def test_batched_last_axis_matches_one_by_one(responses):
    t = np.stack([np.asarray(r.time) for r in responses[:3]])
    y = np.stack([np.asarray(r.position) for r in responses[:3]])
    r = np.stack([np.asarray(r.reference) for r in responses[:3]])
    batch = smooth_step_info(time=t, position=y, reference=r, width=1e-3)
    for i in range(3):
        one = smooth_step_info(responses[i], width=1e-3)
        for a, b in zip(batch, one, strict=True):
            assert float(a[i]) == pytest.approx(float(b), rel=1e-12)


def test_building_blocks():
    x = jnp.linspace(-2.0, 2.0, 9)
    s = smooth_step(x)
    assert float(s[0]) == 0.0 and float(s[-1]) == 1.0 and float(s[4]) == 0.5
    assert np.all(np.diff(np.asarray(s)) >= 0)
    z = jnp.asarray([0.0, 0.3, 1.0, 0.2])
    assert float(soft_max(z, 1e-4)) == pytest.approx(1.0, abs=1e-9)
    assert float(soft_max(z, 1.0)) < 1.0  # from below: no log(n) bias upward


@pytest.fixture(scope="module")
def grads():
    """Gradients of each surrogate w.r.t. (kp, kd, ki) through the smooth simulator."""
    plant = jc.handout_plant()
    exp = jc.step(0.5, horizon=2.0)

    def metrics(g, width):
        pid = jc.PID(kp=g[0], kd=g[1], ki=g[2], v_limit=6.0)
        res = jc.simulate(plant, pid, exp, smoothing=jc.Smoothing(voltage=0.1))
        return jnp.stack(
            [
                settling_time(res.time, res.position, res.reference, width=width),
                overshoot(res.position, res.reference, width=width),
                rise_time(res.time, res.position, res.reference, width=width),
                steady_state_error(res.position, res.reference, width=width),
            ]
        )

    f = jax.jit(metrics)
    jac = jax.jit(jax.jacrev(metrics))
    g0 = jnp.asarray([60.0, 2.0, 1.0])
    return f, jac, g0


def test_gradients_finite_nonzero_and_match_finite_differences(grads):
    f, jac, g0 = grads
    width = 4e-3  # the tuner's starting width
    J = np.asarray(jac(g0, width))
    assert np.all(np.isfinite(J))
    # Every metric depends on kp and kd here (overshoot 10 %, slow settling).
    assert np.all(np.abs(J[:, :2]) > 0), J
    # Central differences, relative step 1e-5 of each gain.
    for j in range(3):
        h = 1e-5 * float(g0[j])
        e = np.zeros(3)
        e[j] = h
        fd = (np.asarray(f(g0 + e, width)) - np.asarray(f(g0 - e, width))) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=2e-3, atol=1e-7 * np.abs(J).max())


def test_gradient_signs_are_physical(grads):
    """More derivative gain, less overshoot; more proportional gain, a shorter rise."""
    _, jac, g0 = grads
    J = np.asarray(jac(g0, 4e-3))
    assert J[1, 1] < 0  # d overshoot / d kd
    assert J[2, 0] < 0  # d rise time / d kp
