"""Step metrics: exact numpy, streamed JAX and python-control's step_info agree."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.batch_metrics import step_metrics_batch
from jaxcart.metrics import StepInfo

TS = 0.001


@pytest.mark.parametrize("kp, kd", [(20.0, 1.0), (60.0, 0.5), (30.0, 4.0)])
def test_step_info_matches_python_control_on_linear_responses(kp, kd):
    plant = jc.Plant(effects=())
    res = jc.simulate(plant, jc.PID(kp=kp, kd=kd), jc.step(0.05, horizon=3.0))
    ours = jc.step_info(res)
    ref = control.step_info(np.asarray(res.position), np.asarray(res.time), yfinal=0.05)
    assert ours.rise_time == pytest.approx(ref["RiseTime"], abs=TS * 1.01)
    assert ours.settling_time == pytest.approx(ref["SettlingTime"], abs=TS * 1.01)
    # Amplitudes to 0.5 % of the step.
    assert ours.overshoot == pytest.approx(ref["Overshoot"], abs=0.5)


def test_streamed_metrics_equal_exact_metrics_of_the_stored_run():
    plant = jc.handout_plant(f_c=0.4)
    pid = jc.PID(kp=45.0, kd=4.0, ki=3.0, v_limit=6.0)
    exp = jc.step(0.5)
    stored = jc.step_info(jc.simulate(plant, pid, exp), v_limit=6.0)
    streamed = jax.jit(jc.step_metrics)(plant, pid, exp)
    for name in (
        "rise_time",
        "settling_time",
        "overshoot",
        "steady_state_error",
        "peak_voltage",
        "saturation_time",
    ):
        assert float(getattr(streamed, name)) == pytest.approx(getattr(stored, name), abs=1e-9)


def test_unsettled_run_has_infinite_settling_time():
    res = jc.simulate(jc.handout_plant(), jc.PID(kp=5.0), jc.step(0.5, horizon=0.5))
    info = jc.step_info(res)
    assert info.settling_time == np.inf and not info.meets()


def test_batch_sharded_matches_single_runs():
    assert len(jax.devices()) == 2  # conftest asks for two host devices
    rng = np.random.default_rng(3)
    gains = np.stack([rng.uniform(10, 100, 37), rng.uniform(0, 8, 37), rng.uniform(0, 20, 37)], 1)
    plant, base, exp = jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5, horizon=1.5)
    info = step_metrics_batch(plant, base, exp, gains, chunk=8)
    for i in (0, 17, 36):
        pid = jc.PID(kp=gains[i, 0], kd=gains[i, 1], ki=gains[i, 2], v_limit=6.0)
        ref = jc.step_info(jc.simulate(plant, pid, exp, smoothing=jc.EXACT_FORMS), v_limit=6.0)
        assert info.settling_time[i] == pytest.approx(ref.settling_time, abs=1e-9)
        assert info.overshoot[i] == pytest.approx(ref.overshoot, abs=1e-9)
        assert info.saturation_time[i] == pytest.approx(ref.saturation_time, abs=1e-9)


def test_batch_float32_close_to_float64():
    gains = np.array([[40.0, 5.0, 0.0], [80.0, 8.0, 2.0]])
    plant, base, exp = jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5)
    f64 = step_metrics_batch(plant, base, exp, gains)
    f32 = step_metrics_batch(plant, base, exp, gains, dtype=jnp.float32)
    assert np.allclose(f32.settling_time, f64.settling_time, atol=2 * TS)
    assert np.allclose(f32.overshoot, f64.overshoot, atol=0.05)


def test_batch_rejects_badly_shaped_gains():
    with pytest.raises(ValueError, match="shape"):
        step_metrics_batch(jc.handout_plant(), jc.PID(), jc.step(0.5), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="chunk"):
        step_metrics_batch(jc.handout_plant(), jc.PID(), jc.step(0.5), np.zeros((4, 3)), chunk=0)


@pytest.mark.parametrize("dtype", [None, jnp.float32])
def test_batch_of_no_gains_is_empty_step_info_of_the_same_dtypes(dtype):
    """Zero rows run nothing and give empty fields with the dtypes a one-row batch has (the
    problem of test_batch_float32_close_to_float64, so the one-row run shares its compile)."""
    plant, base, exp = jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5)
    one = step_metrics_batch(plant, base, exp, np.array([[40.0, 5.0, 0.0]]), dtype=dtype)
    seen = []
    none = step_metrics_batch(
        plant, base, exp, np.zeros((0, 3)), dtype=dtype, progress=lambda *a: seen.append(a)
    )
    assert isinstance(none, StepInfo) and seen == []
    for name, got in none._asdict().items():
        want = getattr(one, name)
        assert isinstance(got, np.ndarray) and got.shape == (0,), name
        assert got.dtype == want.dtype, name
    plants = [plant, plant.replace(B_eq=3.0)]  # a plant set: the worst, still one per row
    assert step_metrics_batch(plants, base, exp, np.zeros((0, 3))).overshoot.shape == (0,)


def test_batch_over_a_plant_set_is_the_worst_of_single_runs():
    """Metrics over a plant set are the field-wise worst of each plant's stored run."""
    plants = [jc.handout_plant().replace(B_eq=b) for b in (3.0, 5.4, 7.0)]
    gains = np.array([[40.0, 5.0, 0.0], [90.0, 3.0, 2.0]])
    base, exp = jc.PID(v_limit=6.0), jc.step(0.5, horizon=1.5)
    info = step_metrics_batch(plants, base, exp, gains)
    for i, g in enumerate(gains):
        pid = jc.PID(kp=g[0], kd=g[1], ki=g[2], v_limit=6.0)
        refs = [
            jc.step_info(jc.simulate(p, pid, exp, smoothing=jc.EXACT_FORMS), v_limit=6.0)
            for p in plants
        ]
        for name in ("settling_time", "overshoot", "rise_time", "peak_voltage"):
            worst = max(getattr(r, name) for r in refs)
            assert getattr(info, name)[i] == pytest.approx(worst, abs=1e-9), name
        assert info.diverged[i] == any(r.diverged for r in refs)
    # The plants differ enough that the worst is not the nominal one's.
    assert len({round(r.overshoot, 6) for r in refs}) == 3


@pytest.mark.parametrize(
    "kp, kd, y0",
    [
        (40.0, 5.0, 0.0),  # settles: not diverged
        (-4000.0, 0.0, 0.0),  # grows past 1 km, finite
        (-1e7, 0.0, 0.0),  # overflows to inf, then NaN
        (40.0, 5.0, 1500.0),  # starts 1.5 km out, comes back within the run
    ],
)
def test_streamed_divergence_flag_matches_the_stored_run(kp, kd, y0):
    """diverged (|y_k| > 1 km or not finite at any sample) is streamed as a running max of
    |y_k|, which propagates NaN: it must agree with the stored run's flag in every case."""
    plant, pid = jc.Plant(effects=()), jc.PID(kp=kp, kd=kd)
    exp = jc.step(0.5, horizon=0.5, y0=y0)
    stored = jc.simulate(plant, pid, exp, smoothing=jc.EXACT_FORMS)
    streamed = jax.jit(jc.step_metrics)(plant, pid, exp, smoothing=jc.EXACT_FORMS)
    assert bool(streamed.diverged) == bool(stored.diverged) == (kp < 0 or y0 > 1e3)
    if kp < 0 or y0 > 1e3:
        assert np.isinf(float(streamed.settling_time)) and np.isinf(float(streamed.overshoot))
