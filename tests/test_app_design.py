"""The design page's numbers (tuning.app.design), each against an independent reference: the
exact simulator called directly, python-control's interconnected loop, the exact simulator's
verdict inside the batched region."""

import math

import numpy as np
import pytest

import jaxcart as jc
from jaxcart import control_systems
from jaxcart.errors import UserError
from jaxcart.exact import simulate_exact
from jaxcart.synthetic import make_recording, make_tap_recording, write_recording
from tuning.app import design as app
from tuning.design.losses import Spec

#: Region points per axis in these tests (the page uses 32): small and fast.
POINTS = 12


@pytest.fixture(scope="module")
def problem():
    return app.DesignProblem(region_points=POINTS)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A synthetic PID step (B_eq 4.6 kg/s, f_c 0.45 N, encoder counts) as an experiment file."""
    truth = jc.build_plant({"B_eq": 4.6, "f_c": 0.45})
    pid = jc.PID(kp=60.0, ki=4.0, kd=6.0, v_limit=6.0)
    rec = make_recording(truth, pid, jc.step(0.3, horizon=2.0, y0=0.1))
    return write_recording(rec, tmp_path_factory.mktemp("rec") / "pid.toml")


def test_the_spec_is_the_tuners():
    assert app.SPEC == Spec()
    assert (app.SPEC.step, app.SPEC.settling_time, app.SPEC.overshoot) == (0.5, 1.0, 5.0)
    assert app.V_LIMIT == 6.0


def test_design_is_the_exact_run_and_its_metrics(problem):
    s = app.Settings(kp=120.0, ki=3.0, kd=9.0, tau=0.005, setpoint=0.5)
    d = problem.design(s)
    pid = jc.PID(kp=120.0, ki=3.0, kd=9.0, tau=0.005, v_limit=6.0)
    ref = simulate_exact(jc.handout_plant(), pid, jc.step(0.5, horizon=3.0))
    np.testing.assert_array_equal(d.response.position, ref.position)
    np.testing.assert_array_equal(d.response.voltage, ref.voltage)
    assert np.max(np.abs(d.response.voltage)) <= 6.0  # the 6 V limit acts
    info = jc.step_info(ref, v_limit=6.0)
    assert d.info == info
    assert d.meets == info.meets(1.0, 5.0)
    checks = {c.name: c for c in d.checks}
    assert checks["settling time"].bound == 1.0 and checks["overshoot"].bound == 5.0
    assert checks["settling time"].ok == (info.settling_time < 1.0)
    assert checks["rise time"].ok is None and checks["rise time"].value == info.rise_time


def test_handout_gains_miss_the_spec_by_settling(problem):
    """kp 40, ki 5, kd 5 creep into the band too late (the integral), overshoot is fine."""
    d = problem.design(app.Settings())
    bad = [c.name for c in d.checks if c.ok is False]
    assert not d.meets and bad == ["settling time"]


def test_setpoint_zero_has_no_step_metrics(problem):
    d = problem.design(app.Settings(setpoint=0.0))
    assert d.info is None and d.checks == () and not d.meets
    assert np.all(d.response.position == 0.0)


@pytest.mark.parametrize(
    "gains", [(40.0, 5.0, 5.0), (150.0, 0.0, 10.0), (80.0, 12.0, 0.0), (30.0, 0.0, 0.0)]
)
@pytest.mark.parametrize("delay", [0.0, 0.0025])
def test_loop_poles_match_python_control(gains, delay):
    kp, ki, kd = gains
    plant = jc.build_plant({"delay": delay}) if delay else jc.handout_plant()
    pid = jc.PID(kp=kp, ki=ki, kd=kd, tau=0.004)
    mine = np.sort_complex(app.loop_poles(plant, pid))
    ref = np.sort_complex(control_systems.closed_loop_poles(plant, pid))
    np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-9)


def test_s_plane_is_the_log_of_z():
    z = np.array([0.99, 0.9 + 0.1j, -0.5, 0.0])
    s = app.s_plane(z, 0.001)
    np.testing.assert_allclose(np.exp(s[:3] * 0.001), z[:3], rtol=1e-12)
    assert np.all(np.isfinite(s)) and s[3].real < -2e4  # z = 0: very fast, not -inf


def test_design_poles_and_stability(problem):
    d = problem.design(app.Settings(kp=60.0, ki=5.0, kd=6.0))
    z = control_systems.closed_loop_poles(jc.handout_plant(), jc.PID(kp=60.0, ki=5.0, kd=6.0))
    np.testing.assert_allclose(
        np.sort_complex(np.exp(d.poles * 0.001)), np.sort_complex(z), atol=1e-9
    )
    assert d.stable == control_systems.is_stable(
        jc.handout_plant(), jc.PID(kp=60.0, ki=5.0, kd=6.0)
    )


def test_region_agrees_with_the_exact_run_inside_each_zone(problem):
    """Every region cell whose 8 neighbours share its status gets the exact simulator's
    verdict (the boundary cells may differ: float32, a 1 ms settling time apart)."""
    s = app.Settings(ki=2.0, tau=0.01, setpoint=0.5)
    region = problem.region_at(s)
    assert region.status.shape == (POINTS, POINTS)
    codes = set(np.unique(region.status).tolist())
    assert app.FEASIBLE in codes and len(codes) >= 2
    interior = []
    st = region.status
    for i in range(1, POINTS - 1):
        for j in range(1, POINTS - 1):
            if np.all(st[i - 1 : i + 2, j - 1 : j + 2] == st[i, j]):
                interior.append((i, j))
    rng = np.random.default_rng(0)
    picks = [interior[k] for k in rng.choice(len(interior), size=8, replace=False)]
    for i, j in picks:
        kp, kd = float(region.kp[j]), float(region.kd[i])
        d = problem.design(app.Settings(kp=kp, ki=2.0, kd=kd, tau=0.01))
        assert d.meets == (st[i, j] == app.FEASIBLE), (kp, kd, st[i, j], d.info)


def test_region_status_codes():
    info = jc.StepInfo(
        rise_time=np.zeros(5),
        settling_time=np.array([0.5, 0.5, 2.0, np.inf, np.inf]),
        overshoot=np.array([1.0, 9.0, 1.0, 9.0, np.inf]),
        steady_state_error=np.zeros(5),
        peak_voltage=np.zeros(5),
        saturation_time=np.zeros(5),
        diverged=np.array([False, False, False, False, True]),
    )
    expected = [app.FEASIBLE, app.OVERSHOOTS, app.SLOW, app.BOTH, app.DIVERGED]
    assert app.region_status(info).tolist() == expected


def test_region_is_kept_while_kp_and_kd_move(problem):
    a = problem.region_at(app.Settings(kp=40.0, kd=5.0, ki=1.0))
    b = problem.region_at(app.Settings(kp=90.0, kd=2.0, ki=1.0))
    c = problem.region_at(app.Settings(kp=90.0, kd=2.0, ki=1.5))
    assert a is b and c is not a and c.ki == 1.5


@pytest.mark.parametrize(
    "name,value", [("kp", math.nan), ("kd", -1.0), ("tau", math.inf), ("setpoint", math.nan)]
)
def test_bad_settings_are_one_line(name, value):
    with pytest.raises(UserError, match=rf"^{name} = .*: ") as exc:
        app.Settings(**{name: value})
    assert "\n" not in str(exc.value)


def test_recording_overlay_starts_the_sliders_at_its_gains(recording):
    problem = app.problem_from_files(data=recording, region_points=POINTS)
    o = problem.overlay
    assert o.name == "pid.toml" and o.time[0] == 0.0
    assert abs(o.y0 - 0.1) < 1e-4 and abs(o.position[0]) < 1e-12
    assert abs(o.reference[-1] - 0.2) < 1e-4  # the step from 0.1 m to 0.3 m, from its start
    assert o.info is not None and o.command is not None
    s = problem.start
    assert (s.kp, s.ki, s.kd) == (60.0, 4.0, 6.0) and abs(s.setpoint - 0.2) < 1e-4
    assert problem.plant_label is None and problem.design(s).nominal is None


def test_recording_that_is_not_a_closed_loop_is_refused(tmp_path):
    tap = make_tap_recording(jc.tap_plant())
    path = write_recording(tap, tmp_path / "tap.toml")
    with pytest.raises(UserError, match=r"^--data .*tap\.toml: a tap experiment; give a"):
        app.problem_from_files(data=path)


def test_fitted_plant_is_the_design_plant(tmp_path):
    fitted = jc.build_plant({"B_eq": 4.6, "f_c": 0.45})
    path = jc.write_plant_file(tmp_path / "P.toml", fitted, fit={"rms_mm": 0.2})
    problem = app.problem_from_files(plant=path, region_points=POINTS)
    assert problem.plant_label == "fitted plant (P.toml)"
    s = app.Settings(kp=60.0, ki=4.0, kd=6.0)
    d = problem.design(s)
    ref = simulate_exact(fitted, s.controller(), jc.step(0.5, horizon=3.0))
    nominal = simulate_exact(jc.handout_plant(), s.controller(), jc.step(0.5, horizon=3.0))
    np.testing.assert_array_equal(d.response.position, ref.position)
    np.testing.assert_array_equal(d.nominal.position, nominal.position)


def test_each_file_is_checked_for_what_it_is(recording, tmp_path):
    """--plant given a recording without a [plant] table is refused with the fix (it holds no
    plant: the handout's would have been drawn as the student's); a recording's own [plant]
    table is used and named as such; a plant file given as --data is refused."""
    with pytest.raises(UserError) as refused:
        app.problem_from_files(plant=recording)
    message = str(refused.value)
    assert message.startswith(f"--plant {recording}: a recording (an experiment file) with no")
    assert "jaxcart fit" in message and f"--data {recording}" in message
    truth = jc.build_plant({"B_eq": 4.6, "f_c": 0.45})
    rec = make_recording(truth, jc.PID(kp=60.0, ki=4.0, kd=6.0, v_limit=6.0), jc.step(0.5))
    own = write_recording(rec, tmp_path / "own.toml", plant_overrides={"B_eq": 4.6, "f_c": 0.45})
    problem = app.problem_from_files(plant=own, region_points=POINTS)
    assert problem.plant_label == "[plant] of own.toml"
    assert (problem.plant.B_eq, problem.plant.structure) == (4.6, ("coulomb",))
    plant = jc.write_plant_file(tmp_path / "P.toml", truth)
    assert app.problem_from_files(plant=plant).plant_label == "plant of P.toml"
    with pytest.raises(UserError, match=r"^--data .*P\.toml: a plant file, not a recording; give"):
        app.problem_from_files(data=plant)
    with pytest.raises(UserError, match=r"^--plant .*nope\.toml: no such file"):
        app.problem_from_files(plant=tmp_path / "nope.toml")


def test_a_design_that_leaves_the_track_is_said(problem):
    """The largest excursion |y - y0| of the exact run against the track's 0.814 m travel
    (the lab's end stops), as jaxcart.plausibility.check_track judges a simulation."""
    from jaxcart.params import TRAVEL
    from jaxcart.plausibility import check_track

    s = app.Settings(kp=200.0, ki=30.0, kd=0.0, setpoint=0.8)
    d = problem.design(s)
    ref = simulate_exact(jc.handout_plant(), s.controller(), jc.step(0.8, horizon=3.0))
    assert d.excursion == float(np.max(np.abs(ref.position))) > TRAVEL
    assert check_track(ref, "run")  # the library's own check says the same
    assert not d.on_track and not d.meets
    checks = {c.name: c for c in d.checks}
    assert checks[app.EXCURSION].bound == TRAVEL and checks[app.EXCURSION].ok is False
    within = problem.design(app.Settings(kp=150.0, ki=1.0, kd=10.0, setpoint=0.5))
    assert within.on_track and within.meets and checks_names(within)[-1] == app.EXCURSION


def checks_names(design):
    return [c.name for c in design.checks]


def test_the_error_at_the_end_of_the_run_is_named_for_what_it_is(problem):
    """step_info's steady_state_error is |r - y| at the last sample: with ki > 0 the integral is
    still closing it at 3 s (the slowest pole near -0.13 1/s), no steady state."""
    d = problem.design(app.Settings())
    assert checks_names(d) == [
        "rise time",
        "settling time",
        "overshoot",
        "error at t = 3 s",
        "peak voltage",
        "time at 6 V",
        app.EXCURSION,
    ]
    error = d.checks[3].value
    assert error == abs(0.5 - float(d.response.position[-1])) > 0.02
