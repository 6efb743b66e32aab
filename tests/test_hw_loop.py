"""The hardware loop against the exact simulator (the same gains and plant, in virtual time),
its recording read back by jaxcart, and a fit of that recording giving back the cart."""

import math

import numpy as np
import pytest
from fakeclock import FakeClock, Stalling

import jaxcart as jc
from hw.control_law import PID
from hw.devices.sim import ENCODER_RESOLUTION, CartParams, SimCart
from hw.loop import run_loop
from hw.safety import Limits
from jaxcart.exact import simulate_exact
from jaxcart.files import read_experiment

Q = ENCODER_RESOLUTION
#: Same closed forms, same control law: the two runs agree to rounding [m].
EXACT_TOL = 1e-9
CONTROLLERS = {
    "pid": PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0),
    "measurement+clamping": PID(
        kp=60.0, kd=4.0, ki=20.0, v_limit=5.0, derivative_on="measurement", anti_windup="clamping"
    ),
    "back-calculation": PID(
        kp=30.0, kd=3.0, ki=30.0, v_limit=4.0, anti_windup="back_calculation", kb=2.0
    ),
}


def _both(pid, f_c, quantization, amplitude=0.5, horizon=3.0, B_eq=5.4):
    plant = jc.handout_plant(f_c=f_c, v_sat=6.0, B_eq=B_eq)
    exp = jc.step(amplitude, horizon=horizon)
    reference = simulate_exact(plant, pid, exp)
    device = SimCart(CartParams(f_c=f_c, B_eq=B_eq, v_sat=6.0, quantization=quantization))
    result = run_loop(device, pid, np.asarray(exp.signal), clock="virtual")
    return reference, result, device


@pytest.mark.parametrize("name", list(CONTROLLERS))
def test_loop_reproduces_the_exact_simulator(name):
    reference, result, _ = _both(CONTROLLERS[name], f_c=0.3, quantization=0.0)
    assert result.status == "completed" and result.fault is None
    assert result.n_samples == reference.position.size
    np.testing.assert_allclose(result.position, reference.position, rtol=0, atol=EXACT_TOL)
    np.testing.assert_allclose(result.command, reference.command, rtol=0, atol=1e-6)
    assert result.command[-1] == pytest.approx(reference.command[-1], abs=1e-6)


def test_quantized_loop_stays_within_one_count_of_the_exact_simulator():
    reference, result, device = _both(CONTROLLERS["pid"], f_c=0.3, quantization=Q)
    counts = result.position / Q
    assert np.abs(counts - np.round(counts)).max() < 1e-6  # whole counts
    error = reference.position - result.position
    assert np.abs(error).max() < Q, np.abs(error).max() / Q
    # The true cart (not the encoder) ends within a count of the exact one too.
    assert abs(device.position - reference.position[-1]) < Q


def test_recording_reads_back_with_every_setting(tmp_path):
    pid = CONTROLLERS["measurement+clamping"]
    device = SimCart(CartParams(f_c=0.2))
    r = np.full(801, 0.3)
    result = run_loop(device, pid, r, clock="virtual", out=tmp_path / "run.toml", notes={"x": 1})
    rec = read_experiment(result.path)
    assert rec.kind == "closed_loop" and rec.sample_time == pid.sample_time
    assert rec.controller == pid
    np.testing.assert_array_equal(rec.position, result.position)
    np.testing.assert_array_equal(rec.command, result.command)
    np.testing.assert_array_equal(rec.reference, 0.3)
    run = rec.meta["run"]
    assert run["status"] == "completed" and run["samples"] == 801 and "fault" not in run
    assert run["last_voltage"] == 0.0 and run["limit_x_max"] == 0.6
    assert rec.meta["device"]["name"] == "sim" and rec.meta["device"]["f_c"] == 0.2
    assert rec.meta["device"]["clock"] == "virtual"
    assert rec.meta["timing"]["samples"] == 801 and rec.meta["timing"]["compute_median_us"] > 0
    assert rec.meta["notes"] == {"x": 1}
    # The timing columns are in the CSV, and ignored as signals.
    header = (tmp_path / "run.csv").read_text().splitlines()[0]
    assert header == "t,y,v,r,e,t_wall,compute"


def test_real_time_loop_paces_on_absolute_deadlines(tmp_path):
    """The perf_counter pacing on a clock the test drives (not the machine's: its load would
    decide the outcome): every sample read at its deadline k Ts, however long the sleeps took
    before; a stall of 3 ms at sample 100 makes that sample late and the next ones catch up
    back-to-back, without moving the schedule. How well a real machine keeps time is measured
    by ``python -m hw bench``, not asserted here."""
    from hw.pacing import verdict

    pid = CONTROLLERS["pid"]
    clock = FakeClock()
    device = Stalling(clock, at=100, seconds=0.003)
    out = tmp_path / "rt.toml"
    result = run_loop(
        device, pid, np.full(201, 0.1), limits=Limits(late_max=0.1), out=out, timer=clock.timer
    )
    assert result.status == "completed", result.fault
    t = result.timing
    late = result.t_wall - result.time
    assert np.all(np.abs(late[:100] - 2e-6) < 1e-6)  # at the deadline, but for the spin's ticks
    np.testing.assert_allclose(late[100:103], [0.003, 0.002, 0.001], atol=2e-5)
    # Caught up by reading 101-103 back-to-back, then on the schedule again: the absolute
    # deadlines do not drift.
    assert np.all(late[104:] < 3e-6) and result.t_wall[-1] == pytest.approx(0.2, abs=3e-6)
    assert t["late_samples"] == 3 and t["catch_up_periods"] == 3 and t["overruns"] == 3
    assert t["real_time"] == "fell behind" and "NOT kept" in verdict(t)
    rec = read_experiment(result.path)
    assert rec.meta["device"]["clock"] == "perf_counter"
    assert rec.meta["timing"]["late_max_us"] == pytest.approx(3000, abs=5)


def test_refuses_a_controller_it_cannot_run_as_tuned():
    with pytest.raises(ValueError, match="v_limit = inf.*v_max = 6"):
        run_loop(SimCart(), PID(kp=10.0), [0.1] * 10, clock="virtual")
    with pytest.raises(ValueError, match="v_limit = 12 V"):
        run_loop(SimCart(), PID(kp=10.0, v_limit=12.0), [0.1] * 10, clock="virtual")
    with pytest.raises(ValueError, match="10 kHz"):
        run_loop(SimCart(), PID(kp=1.0, v_limit=6, sample_time=1e-5), [0.1] * 10)


HW_TRUTH = {"B_eq": 2.5, "f_c": 0.3}


@pytest.fixture(scope="module")
def hw_recording(tmp_path_factory):
    """A P 50 step run by the loop on the simulated cart (Coulomb friction, 6 V amplifier,
    quantization), read back from the experiment file it wrote."""
    truth = HW_TRUTH
    device = SimCart(CartParams(B_eq=truth["B_eq"], f_c=truth["f_c"], quantization=Q))
    out = tmp_path_factory.mktemp("hw") / "p"
    result = run_loop(
        device, PID(kp=50.0, v_limit=6.0), np.full(1501, 0.4), clock="virtual", out=out
    )
    return read_experiment(result.path)


@pytest.mark.slow
def test_diagnose_of_a_hardware_recording_names_the_carts_friction(hw_recording):
    from tuning.estimation.diagnose import diagnose

    d = diagnose([hw_recording], progress=False)
    assert d.left_out == ["coulomb"], d.left_out
    assert d.parameters["f_c"]["value"] == pytest.approx(HW_TRUTH["f_c"], rel=0.05)
    assert d.parameters["B_eq"]["value"] == pytest.approx(HW_TRUTH["B_eq"], rel=0.03)
    assert d.rms_after < 1.5 * Q / math.sqrt(12) < d.rms_before


@pytest.mark.slow
def test_fit_of_a_hardware_recording_gives_back_the_cart(hw_recording):
    from tuning.estimation import fit

    truth = HW_TRUTH
    rec = hw_recording
    fitted = fit.fit([rec], ("B_eq", "f_c"), progress=False)
    b, f = fitted.params["B_eq"], fitted.params["f_c"]
    print(f"hw recording fit: B_eq = {b.value:.4g} +/- {b.stderr:.2g}, f_c = {f.value:.4g}")
    assert b.value == pytest.approx(truth["B_eq"], rel=0.03)
    assert f.value == pytest.approx(truth["f_c"], rel=0.05)
    assert fitted.rms_after_exact < 1.5 * Q / math.sqrt(12)
