"""The smooth simulator against independent references: python-control on the linear loop, the
handout's tap solution (1.2), finite differences for gradients."""

import dataclasses

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc

TS = 0.001


def discrete_loop(plant, pid, ts=TS):
    """Closed loop y/r of the sampled-data loop built with python-control (c2d ZOH + discrete
    PID transfer functions); derivative on measurement enters through the feedback path."""
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    P = control.c2d(control.tf([gamma], [m, c, 0.0]), ts, method="zoh")
    z = control.tf([1, 0], [1], ts)
    C_pi = pid.kp + pid.ki * ts / (z - 1)
    C_d = pid.kd * (z - 1) / ((pid.tau + ts) * z - pid.tau)
    if pid.derivative_on == "error":
        return control.feedback(P * (C_pi + C_d), 1)
    # u = C_pi r - (C_pi + C_d) y, in state space (tf division would cancel poles numerically).
    return control.series(control.ss(C_pi), control.feedback(control.ss(P), control.ss(C_pi + C_d)))


@pytest.mark.parametrize(
    "pid",
    [
        jc.PID(kp=20.0),
        jc.PID(kp=30.0, ki=8.0),
        jc.PID(kp=40.0, kd=2.0, ki=5.0),
        jc.PID(kp=40.0, kd=2.0, ki=5.0, derivative_on="measurement"),
        jc.PID(kp=40.0, kd=2.0, tau=0.0),
    ],
    ids=["P", "PI", "PID-error", "PID-measurement", "PD-unfiltered"],
)
def test_linear_loop_matches_python_control(pid):
    """No saturation reached, no friction: the loop is LTI and python-control is exact."""
    plant = jc.Plant(effects=())
    n = 1501
    r = np.full(n, 0.05)
    r[0] = 0.0  # step at the first sample after t=0: both sides then start from e_-1 = e_0 = 0
    res = jc.simulate(plant, pid, jc.reference_sequence(r))
    t = np.arange(n) * TS
    _, y_ref = control.forced_response(discrete_loop(plant, pid), t, r)
    assert np.max(np.abs(np.asarray(res.position) - y_ref)) < 1e-6  # metres
    assert not bool(res.diverged)


def test_tap_matches_handout_solution():
    """Handout (1.2), motor unplugged: y = y0 + (m v0 / B_eq)(1 - exp(-B_eq t / m))."""
    plant = jc.tap_plant(B_eq=4.0)
    y0, v0 = 0.1, 0.6
    res = jc.simulate(plant, jc.PID(), jc.tap(v0, horizon=2.0, y0=y0))
    t = np.asarray(res.time)
    m, b = float(plant.m), 4.0
    y_ref = y0 + m * v0 / b * (1 - np.exp(-b * t / m))
    assert np.max(np.abs(np.asarray(res.position) - y_ref)) < 1e-6
    assert np.allclose(np.asarray(res.voltage), 0.0)


def test_open_loop_step_matches_analytic():
    plant = jc.Plant(effects=())
    res = jc.simulate(plant, jc.PID(), jc.voltage_step(2.0, horizon=1.0))
    t = np.asarray(res.time)
    m, c, f = float(plant.m), float(plant.c), 2.0 * float(plant.gamma)
    y_ref = f / c * (t - m / c * (1 - np.exp(-c * t / m)))
    assert np.max(np.abs(np.asarray(res.position) - y_ref)) < 1e-9


def loss(gains, params):
    kp, kd, ki = gains
    b_eq, f_c = params
    plant = jc.handout_plant(f_c=0.5).replace(B_eq=b_eq, f_c=f_c)
    pid = jc.PID(kp=kp, kd=kd, ki=ki, v_limit=6.0)
    res = jc.simulate(plant, pid, jc.step(0.3, horizon=0.6))
    return jnp.sum(res.error**2) * TS + jnp.sum(res.command**2) * TS * 1e-3


def test_gradients_match_central_differences():
    gains = jnp.array([30.0, 2.0, 4.0])
    params = jnp.array([5.4, 0.5])
    g_gains, g_params = jax.jit(jax.grad(loss, argnums=(0, 1)))(gains, params)
    f = jax.jit(loss)
    for x, g, which in ((gains, g_gains, 0), (params, g_params, 1)):
        for i in range(x.shape[0]):
            h = 1e-5 * max(1.0, abs(float(x[i])))
            dx = jnp.zeros_like(x).at[i].set(h)
            args = [gains, params]
            args[which] = x + dx
            up = f(*args)
            args[which] = x - dx
            fd = (up - f(*args)) / (2 * h)
            assert float(g[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-10)
            assert float(g[i]) != 0.0


def test_no_recompile_when_values_change():
    traces = []

    @jax.jit
    def sim(plant, pid, exp):
        traces.append(1)  # runs only when jax traces (and so compiles) anew
        return jc.simulate(plant, pid, exp)

    exp = jc.step(0.5, horizon=0.3)
    sim(jc.handout_plant(f_c=0.2), jc.PID(kp=40.0, v_limit=6.0), exp)
    sim(jc.handout_plant(f_c=0.7, B_eq=3.0), jc.PID(kp=10.0, kd=3.0, v_limit=5.0), exp)
    sim(jc.handout_plant(f_c=0.2), jc.PID(kp=40.0, v_limit=6.0), jc.step(0.2, horizon=0.3))
    assert len(traces) == 1
    sim(jc.handout_plant(f_c=0.2), jc.PID(kp=40.0, derivative_on="measurement"), exp)
    assert len(traces) == 2  # a static setting does retrace: the counter can fail


def test_vmap_over_gains_and_plants_agrees_with_single_runs():
    exp = jc.step(0.5, horizon=0.5)
    kps = jnp.array([20.0, 40.0, 60.0])
    beqs = jnp.array([3.0, 5.4, 7.0])

    def run(kp, b_eq):
        plant = jc.handout_plant(f_c=0.3).replace(B_eq=b_eq)
        return jc.simulate(plant, jc.PID(kp=kp, kd=3.0, v_limit=6.0), exp).position

    batched = jax.vmap(run)(kps, beqs)
    for i in range(3):
        assert np.allclose(batched[i], run(kps[i], beqs[i]), atol=1e-12)


def test_float32_runs_and_agrees_with_float64():
    exp = jc.step(0.5)
    pid = jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
    plant = jc.handout_plant()
    f32 = lambda tree: jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), tree)  # noqa: E731
    r32 = jc.simulate(f32(plant), f32(pid), f32(exp))
    r64 = jc.simulate(plant, pid, exp)
    assert r32.position.dtype == jnp.float32 and r64.position.dtype == jnp.float64
    assert np.max(np.abs(np.asarray(r32.position) - np.asarray(r64.position))) < 1e-4


def test_divergence_is_flagged_not_hidden():
    unstable = jc.PID(kp=10.0, ki=400.0)  # far above the Routh bound c k / m ~ 122
    res = jc.simulate(jc.Plant(effects=()), unstable, jc.step(0.1, horizon=10.0))
    assert bool(res.diverged)
    fine = jc.simulate(jc.Plant(effects=()), jc.PID(kp=10.0, ki=50.0), jc.step(0.1, horizon=10.0))
    assert not bool(fine.diverged)


def test_smoothed_saturation_respects_limit_and_exact_forms_clip():
    exp = jc.step(0.5, horizon=0.2)
    pid = jc.PID(kp=100.0, v_limit=6.0)
    smooth = jc.simulate(jc.handout_plant(), pid, exp)
    hard = jc.simulate(jc.handout_plant(), pid, exp, smoothing=jc.EXACT_FORMS)
    assert float(jnp.max(hard.voltage)) == 6.0
    assert 5.9 < float(jnp.max(smooth.voltage)) <= 6.0


def test_controller_and_experiment_sample_times_must_agree():
    with pytest.raises(ValueError, match="sample_time"):
        jc.simulate(jc.handout_plant(), jc.PID(kp=1.0, sample_time=0.002), jc.step(0.1))


def test_replace_keeps_pid_a_pytree():
    pid = dataclasses.replace(jc.PID(kp=1.0), kd=jnp.asarray(2.0))
    leaves = jax.tree_util.tree_leaves(pid)
    assert len(leaves) == 6


def test_breakaway_from_rest_is_not_held_back_by_narrow_friction_smoothing():
    """Starting at rest with the drive above f_c, the smooth cart at a narrow friction width
    follows the exact stick-slip simulator (one linearization at v = 0 lagged it ~0.1 mm)."""
    from jaxcart.exact import simulate_exact

    plant, pid = jc.handout_plant(f_c=0.5), jc.PID(kp=50.0, v_limit=6.0)
    exp = jc.step(0.4, horizon=0.3)
    exact = np.asarray(simulate_exact(plant, pid, exp).position)
    smooth = jc.simulate(plant, pid, exp, smoothing=jc.Smoothing().scaled(0.01))
    assert abs(float(smooth.position[100]) - exact[100]) < 1e-5  # m, at t = 0.1 s
