"""Before and after a run: the gains' plausibility on hw's simulated cart (against jaxcart's
own closed-loop poles), the step metrics (against jaxcart.metrics.step_info), the honest pacing
verdict and the watchdog chosen for the machine."""

import numpy as np
import pytest

import jaxcart as jc
from hw.cli import main
from hw.control_law import PID
from hw.gains import write_gains
from hw.pacing import WATCHDOG_MAX, WATCHDOG_MIN, choose_watchdog, timing_stats, verdict
from hw.prerun import check_gains, closed_loop_matrix
from hw.stepinfo import run_metrics, segments, spec_of, step_metrics
from jaxcart.metrics import step_info
from jaxcart.plausibility import closed_loop_eigenvalues

LAB = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
STEP = np.full(2001, 0.3)


@pytest.mark.parametrize(
    "pid",
    [
        LAB,
        PID(kp=250.0, kd=10.0, ki=0.94, v_limit=6.0),
        PID(kp=1e6, v_limit=6.0),
        PID(kp=60.0, kd=4.0, ki=20.0, tau=0.0, v_limit=6.0, derivative_on="measurement"),
        PID(kp=300.0, kd=-5.0, ki=400.0, v_limit=6.0),
    ],
)
def test_poles_agree_with_jaxcarts_closed_loop(pid):
    """hw's numpy closed loop against jaxcart.plausibility's, built independently: 1e-9."""
    ours = np.sort_complex(np.linalg.eigvals(closed_loop_matrix(pid)))
    theirs = np.asarray(closed_loop_eigenvalues(pid, jc.handout_plant()))
    theirs = np.sort_complex(theirs[np.abs(theirs) > 1e-12])  # jaxcart carries no s_prev pole
    ours = ours[np.abs(ours) > 1e-12]
    np.testing.assert_allclose(np.abs(ours).max(), np.abs(theirs).max(), rtol=1e-9)


def test_a_relay_and_an_unstable_loop_are_refused_the_lab_gains_are_not():
    assert check_gains(LAB, STEP).refusals == ()
    relay = check_gains(PID(kp=1e6, v_limit=6.0), STEP)
    assert any(r.startswith("relay") for r in relay.refusals) and relay.flips_per_s > 5
    assert relay.at_limit > 0.9
    unstable = check_gains(PID(kp=50.0, kd=-10.0, v_limit=6.0), STEP)  # negative damping
    assert any(r.startswith("unstable") for r in unstable.refusals), unstable.refusals


@pytest.mark.parametrize("fraction, stable", [(0.97, True), (1.03, False)])
def test_the_integral_gain_is_refused_at_the_routh_bound(fraction, stable):
    """PI on m y'' + c y' = gamma u is stable for ki < c kp / m (Routh, continuous time); at
    1 kHz the discrete loop agrees within 3 % of the bound."""
    from hw.devices.sim import CartParams

    p = CartParams()
    pid = PID(kp=50.0, ki=fraction * p.c * 50.0 / p.m, v_limit=6.0)
    refused = [r for r in check_gains(pid, STEP).refusals if r.startswith("unstable")]
    assert (not refused) == stable, refused


def test_the_command_refuses_them_in_one_line_unless_forced(tmp_path, capsys):
    gains = str(write_gains(tmp_path / "relay.json", PID(kp=1e6, v_limit=6.0)))
    out = tmp_path / "r.toml"
    assert main(["run", gains, "--duration", "0.5", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "relay" in err and "--force" in err and err.count("\n") == 1
    assert not out.exists()  # refused before anything: no recording
    status = main(["run", gains, "--duration", "0.5", "--out", str(out), "--force"])
    err = capsys.readouterr().err
    assert "warning (--force): relay" in err
    assert status in (0, 1) and "relay" in jc_notes(out)["forced"]


def jc_notes(out):
    from jaxcart.files import read_experiment

    return read_experiment(out).meta["notes"]


def test_step_metrics_agree_with_jaxcart():
    from hw.devices.sim import SimCart
    from hw.loop import run_loop

    result = run_loop(SimCart(), LAB, np.full(3001, 0.4), clock="virtual")
    ours = run_metrics(result)[0]
    response = jc.Response(
        time=result.time,
        position=result.position,
        velocity=np.zeros_like(result.position),
        reference=result.reference,
        error=result.reference - result.position,
        command=result.command,
        voltage=result.command,
        diverged=False,
    )
    theirs = step_info(response, v_limit=6.0)._asdict()
    for name in ("rise_time", "settling_time", "overshoot", "steady_state_error", "peak_voltage"):
        assert ours[name] == pytest.approx(theirs[name], rel=1e-12, abs=1e-15), name


def test_slider_runs_are_judged_per_set_point():
    assert segments([0.2] * 5 + [0.0] * 5 + [-0.2] * 5) == [(0, 5), (5, 10), (10, 15)]
    t = np.arange(6) * 0.1
    m = step_metrics(t, [0.0, 0.5, 0.9, 1.05, 1.0, 1.0], np.ones(6), [6, 6, 3, 0, 0, 0])
    assert m["overshoot"] == pytest.approx(5.0) and m["settling_time"] == pytest.approx(0.4)
    assert spec_of({"spec": {"settling_time": 2.0}}) == {"settling_time": 2.0, "overshoot": 5.0}


def test_a_loop_that_fell_behind_is_not_shown_as_healthy():
    """A 50 ms pause then the catch-up of an absolute schedule: the median period is exactly
    Ts, yet the verdict says the loop fell behind, with the count and the latest sample."""
    ts, n = 1e-3, 1000
    t_wall = np.arange(n) * ts
    t_wall[400:450] = t_wall[450]  # 50 samples read back-to-back at 0.45 s, with the 451st
    stats = timing_stats(t_wall, np.full(n, 5e-6), ts)
    assert stats["period_median_us"] == pytest.approx(1000.0)
    assert stats["late_samples"] == 50 and stats["catch_up_periods"] == 50
    assert stats["real_time"] == "fell behind"
    line = verdict(stats)
    assert "NOT kept" in line and "50 of 1000" in line and "does not describe" in line
    steady = timing_stats(np.arange(n) * ts + 1e-5, np.full(n, 5e-6), ts)
    assert steady["real_time"] == "kept" and "real time kept" in verdict(steady)


def test_the_watchdog_is_chosen_for_the_machine():
    quiet, how = choose_watchdog(1e-3, probe=lambda ts: 1e-4)
    assert quiet == WATCHDOG_MIN and "probe" in how and "--watchdog" not in how
    busy, how = choose_watchdog(1e-3, probe=lambda ts: 4e-3)
    assert busy == pytest.approx(0.02)
    swamped, how = choose_watchdog(1e-3, probe=lambda ts: 0.03)
    assert swamped == WATCHDOG_MAX and "too busy" in how and "--watchdog S" in how


def test_ctrl_c_during_the_check_drives_nothing(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the gains are simulated before the run: exit 130, nothing started, no file."""
    import hw.cli
    import hw.prerun
    from hw.devices.sim import SimCart

    class Interrupted(SimCart):
        def read(self):
            if getattr(self, "reads", 0) == 10:
                raise KeyboardInterrupt
            self.reads = getattr(self, "reads", 0) + 1
            return super().read()

    started = []

    class Device(SimCart):
        def start(self, sample_time):
            started.append(sample_time)
            super().start(sample_time)

    monkeypatch.setattr(hw.prerun, "SimCart", Interrupted)
    monkeypatch.setattr(hw.cli, "make_device", lambda args: Device())
    gains = str(write_gains(tmp_path / "g.json", LAB))
    out = tmp_path / "never.toml"
    assert main(["run", gains, "--duration", "0.5", "--out", str(out)]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert started == [] and not out.exists() and not out.with_suffix(".csv").exists()


def test_gains_run_at_a_sample_time_in_ms_say_so():
    """A gains file with sample_time 1 (meant as 1 ms): the refusal names the sample time, not
    only the gains."""
    check = check_gains(PID(kp=406.9, ki=0.84, kd=8.5, v_limit=6.0, sample_time=1.0), STEP)
    assert any("sample time of 1 s" in r and "in ms?" in r for r in check.refusals)
