"""The one control law, evaluated by numpy (the hardware loop) and by JAX (the simulator)."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from hw.control_law import pid_init, pid_update


def run_law(pid, r, y, xp):
    state = pid_init(pid, r[0], y[0], xp=xp)
    us, vs = [], []
    for rk, yk in zip(r, y, strict=True):
        u, v, state = pid_update(pid, state, rk, yk, xp=xp)
        us.append(u)
        vs.append(v)
    return np.array(us, dtype=float), np.array(vs, dtype=float)


@pytest.mark.parametrize(
    "derivative_on, anti_windup",
    list(itertools.product(("error", "measurement"), ("none", "clamping", "back_calculation"))),
)
def test_numpy_and_jax_agree(derivative_on, anti_windup):
    rng = np.random.default_rng(1)
    n = 300
    r = np.where(np.arange(n) > 20, 0.4, 0.0)
    y = np.cumsum(rng.normal(0, 2e-3, n))
    pid = jc.PID(
        kp=50.0,
        ki=20.0,
        kd=3.0,
        tau=0.005,
        v_limit=6.0,
        kb=2.0,
        derivative_on=derivative_on,
        anti_windup=anti_windup,
    )
    u_np, v_np = run_law(pid, r, y, np)

    def scan_law(r, y):
        def body(state, ry):
            u, v, state = pid_update(pid, state, ry[0], ry[1], xp=jnp)
            return state, (u, v)

        _, (u, v) = jax.lax.scan(body, pid_init(pid, r[0], y[0], xp=jnp), (r, y))
        return u, v

    u_jx, v_jx = jax.jit(scan_law)(jnp.asarray(r), jnp.asarray(y))
    assert np.max(np.abs(u_np - np.asarray(u_jx))) < 1e-12
    assert np.max(np.abs(v_np - np.asarray(v_jx))) < 1e-12
    assert np.max(np.abs(u_np)) <= 6.0


def test_law_matches_design_equations_by_hand():
    """Two samples worked by hand from the equations of docs/design.md, "The control law"."""
    pid = jc.PID(kp=2.0, ki=10.0, kd=0.5, tau=0.01, sample_time=0.001)
    state = pid_init(pid, 1.0, 0.0)
    u0, _, state = pid_update(pid, state, 1.0, 0.0)
    assert u0 == pytest.approx(2.0)  # e0 = 1, I0 = 0, d0 = 0 (s_-1 = s_0)
    u1, _, state = pid_update(pid, state, 1.0, 0.1)
    d1 = (0.01 * 0.0 + 0.9 - 1.0) / 0.011
    assert u1 == pytest.approx(2.0 * 0.9 + 10.0 * 0.001 + 0.5 * d1)


def test_clamping_holds_integral_only_when_pushing_into_the_limit():
    pid = jc.PID(kp=100.0, ki=50.0, v_limit=6.0, anti_windup="clamping")
    state = pid_init(pid, 0.5, 0.0)
    _, _, state = pid_update(pid, state, 0.5, 0.0)  # v = 50 V, saturated and pushing
    assert state.integral == 0.0
    _, _, state = pid_update(pid, state, 0.5, 0.49)  # v = 1 V, inside the limits
    assert state.integral == pytest.approx(0.001 * 0.01)


def test_bad_settings_are_refused_with_the_field_named():
    with pytest.raises(ValueError, match="derivative_on"):
        jc.PID(derivative_on="rate")
    with pytest.raises(ValueError, match="anti_windup"):
        jc.PID(anti_windup="clip")
    with pytest.raises(ValueError, match="tau"):
        jc.PID(tau=-0.1)
    with pytest.raises(ValueError, match="v_limit is infinite"):
        jc.PID(ki=1.0, anti_windup="clamping")
