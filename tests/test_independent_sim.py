"""The independent generator (tuning.verification) against independent references, each with a
stated tolerance: python-control's discretised closed loop, the tap's closed form under Coulomb
and viscous friction, Karnopp's stick and breakaway, its own sub-step convergence, the lab's
control law in hw/, and jaxcart's exact simulator on the physics both have (the two simulators
checking each other)."""

import math

import control
import numpy as np
import pytest

import jaxcart as jc
from hw.control_law import pid_init, pid_update
from hw.gains import write_gains
from jaxcart.files import read_experiment
from tuning.verification import NONE, REALISTIC, TrueCart, make_recording, run_controller, simulate
from tuning.verification import experiments as ex
from tuning.verification.controller import DiscretePID

TS = 0.001
#: A Karnopp band this narrow stops a cart within (1e-6 m/s)^2 / (2 a) of where an event-exact
#: stop does: what the comparisons with closed forms and jaxcart's exact simulator use.
NARROW = 1e-6


def discrete_loop(cart: TrueCart, pid):
    """y/r of the sampled loop by python-control: ZOH cart (c2d of its state space) and the
    PID's transfer functions, derivative on measurement through the feedback path. The loop is
    closed in state space: closed on transfer functions (polynomial products with two poles at
    z = 1), the PID loop's reference itself drifted 2e-9 m in 0.6 s on some machines."""
    c = cart.B_eq + cart.force_per_amp * cart.emf_per_speed / cart.Rm
    plant = control.c2d(control.ss(control.tf([cart.gamma], [cart.m, c, 0.0])), TS, method="zoh")
    z = control.tf([1, 0], [1], TS)
    c_pi = pid.kp + pid.ki * TS / (z - 1)
    c_d = pid.kd * (z - 1) / ((pid.tau + TS) * z - pid.tau)
    if pid.derivative_on == "error":
        return control.feedback(plant * control.ss(c_pi + c_d), 1)
    return control.series(control.ss(c_pi), control.feedback(plant, control.ss(c_pi + c_d)))


@pytest.mark.parametrize(
    "pid",
    [
        jc.PID(kp=40.0, kd=3.0, ki=5.0),
        jc.PID(kp=40.0, kd=3.0, ki=5.0, derivative_on="measurement"),
        jc.PID(kp=30.0, kd=2.0, tau=0.0),
    ],
    ids=["PID-error", "PID-measurement", "PD-unfiltered"],
)
def test_linear_loop_matches_python_control(pid):
    """No friction, no limit: the loop is LTI and python-control's is exact (1e-9 m)."""
    cart = TrueCart(B_eq=4.6)
    r = np.full(601, 0.05)
    r[0] = 0.0  # step after the first sample: both sides start from e_-1 = e_0 = 0
    run = simulate(cart, ex.reference_sequence(pid, r), NONE)
    _, y_ref = control.forced_response(discrete_loop(cart, pid), np.arange(r.size) * TS, r)
    assert np.max(np.abs(run.position - y_ref)) < 1e-9


def test_tap_coasts_as_the_closed_form_under_coulomb_and_viscous_friction():
    """After the push: m y'' = -B y' - f_c, y' = (v0 + f_c/B) e^{-B t/m} - f_c/B until it stops
    at t_s = (m/B) ln(1 + B v0/f_c), then rest (1e-9 m)."""
    b, f_c = 1.5, 0.4
    cart = TrueCart(B_eq=b, f_c=f_c, v_band=NARROW)
    run = simulate(cart, ex.tap(speed=0.5, rest=0.1, horizon=1.2), NONE)
    shape, length, _ = run.push
    k0 = int(math.ceil((0.1 + length) / TS)) + 1  # the first sample after the push
    t = run.time[k0:] - run.time[k0]
    y0, v0, m = run.true_position[k0], run.velocity[k0], cart.m
    t_stop = m / b * math.log1p(b * v0 / f_c)
    tt = np.minimum(t, t_stop)
    y_ref = y0 + m / b * (v0 + f_c / b) * -np.expm1(-b * tt / m) - f_c / b * tt
    assert t_stop < t[-1]  # it does stop within the run
    assert np.max(np.abs(run.true_position[k0:] - y_ref)) < 1e-9
    assert shape == "rectangle" and 0.45 < v0 < 0.5  # the push reached 0.5 m/s, then slowed


def test_a_force_within_the_static_level_leaves_the_cart_stuck():
    """gamma V = 1.2 N: above the kinetic 0.8 N, below the static 1.5 N: the cart never moves."""
    cart = TrueCart(B_eq=4.6, f_c=0.8, f_s=1.5, v_stribeck=0.002)
    volts = 1.2 / cart.gamma
    run = simulate(cart, ex.voltage_step(volts, horizon=0.5), NONE)
    assert np.all(run.true_position == 0.0) and np.all(run.velocity == 0.0)
    moved = simulate(cart, ex.voltage_step(1.6 / cart.gamma, horizon=0.2), NONE)
    assert moved.true_position[-1] > 1e-4  # beyond the static level it slides


@pytest.mark.parametrize("v_stribeck", [0.0, 0.003])
def test_a_voltage_ramp_breaks_away_at_f_s_over_gamma_rate_with_a_lurch(v_stribeck):
    """A 0.3 V/s ramp: the held command first exceeds f_s at the sample after
    t = f_s / (gamma rate) (within one sample); then friction falls to the kinetic level (at
    once, or over the Stribeck speed) and the cart lurches: within 0.2 s its acceleration
    exceeds half of (f_s - f_c) / m, where a ramp against kinetic friction alone would creep."""
    rate, f_s, f_c = 0.3, 1.2, 0.5
    cart = TrueCart(B_eq=4.6, f_c=f_c, f_s=f_s, v_stribeck=v_stribeck)
    run = simulate(cart, ex.voltage_ramp(rate, horizon=2.6), NONE)
    t_break = f_s / (cart.gamma * rate)
    k = int(np.argmax(run.true_position > 0))
    assert t_break <= run.time[k] <= t_break + 2 * TS
    a = np.diff(run.velocity[k : k + 200]) / TS
    assert a.max() > 0.5 * (f_s - f_c) / cart.m


def test_halving_the_sub_step_moves_positions_by_under_1e_8_m():
    """Stick-slip hunting under PI (the cart stuck in about 40 % of the samples) with Stribeck
    friction, a current limit, a spring, an amplifier lag, jitter and drift; and a square wave
    through the current limit: 40 sub-steps a sample against 80 agree to 1e-8 m (0.04 % of an
    encoder count)."""
    cart = TrueCart(B_eq=3.0, f_c=0.6, f_s=1.2, v_stribeck=0.002, i_max=1.0, k_s=4.0, lag=2e-4)
    art = REALISTIC.replace(quantization=0.0, reads_counts=False)
    hunting = ex.square(jc.PID(kp=40.0, ki=400.0, kd=1.5, v_limit=6.0), 0.01, period=0.4,
                        horizon=0.8)  # fmt: skip
    moves = ex.square(jc.PID(kp=50.0, kd=2.0, v_limit=6.0), 0.1, period=0.5, horizon=0.5)
    stuck = []
    for e in (hunting, moves):
        coarse = simulate(cart, e, art, seed=3, substeps=40)
        fine = simulate(cart, e, art, seed=3, substeps=80)
        assert np.max(np.abs(coarse.true_position - fine.true_position)) < 1e-8
        stuck.append(np.mean(coarse.velocity == 0.0))
    assert stuck[0] > 0.2  # it does hunt by stick-slip


@pytest.mark.parametrize("derivative_on", ["error", "measurement"])
@pytest.mark.parametrize("anti_windup", ["none", "clamping", "back_calculation"])
def test_the_control_law_written_again_matches_hw(derivative_on, anti_windup):
    """tuning.verification.controller against hw.control_law on the same inputs (1e-12 V)."""
    pid = jc.PID(
        kp=50.0, ki=30.0, kd=3.0, tau=0.005, v_limit=4.0, kb=2.0,
        derivative_on=derivative_on, anti_windup=anti_windup,
    )  # fmt: skip
    rng = np.random.default_rng(2)
    r = np.where(np.arange(400) > 10, 0.3, 0.0)
    y = np.cumsum(rng.normal(0.0, 2e-3, r.size))
    law = DiscretePID(pid)
    law.start(r[0], y[0])
    state = pid_init(pid, r[0], y[0])
    for rk, yk in zip(r, y, strict=True):
        u_hw, v_hw, state = pid_update(pid, state, rk, yk)
        u, v = law.update(rk, yk)
        assert abs(u - float(u_hw)) < 1e-12 and abs(v - float(v_hw)) < 1e-12


PID_LAB = jc.PID(kp=40.0, kd=3.0, v_limit=6.0)
SHARED = {
    "saturation + coulomb": ({"B_eq": 4.6, "f_c": 0.3, "v_sat": 4.0}, PID_LAB, 0.4),
    "delay 2.5 ms + coulomb": (
        {"B_eq": 4.6, "delay": 0.0025, "f_c": 0.3},
        jc.PID(kp=60.0, kd=4.0, v_limit=6.0),
        0.3,
    ),
    "current limit + coulomb": ({"B_eq": 4.6, "i_max": 1.5, "f_c": 0.2}, PID_LAB, 0.4),
    "spring under PID": (
        {"B_eq": 4.6, "k_s": 3.0, "y_rest": 0.05, "f_c": 0.2},
        jc.PID(kp=40.0, kd=3.0, ki=10.0, v_limit=6.0),
        0.3,
    ),
    "stiction under PI": (
        {"B_eq": 4.6, "f_c": 0.4, "f_s": 0.6},
        jc.PID(kp=40.0, ki=400.0, kd=1.5),
        0.01,
    ),
    "deadzone": ({"B_eq": 4.6, "deadzone": 0.4}, PID_LAB, 0.3),
}


@pytest.mark.parametrize("name", list(SHARED))
def test_agrees_with_jaxcarts_exact_simulator_on_shared_physics(name):
    """Artefacts off, a narrow band: the two simulators, written apart, agree to 2e-7 m (a
    hundredth of an encoder count) over 1.2 s, and on the commands sent to 1e-4 V."""
    values, pid, amplitude = SHARED[name]
    ref = jc.simulate(
        jc.build_plant(values), pid, jc.step(amplitude, horizon=1.2), solver=jc.Exact()
    )
    run = simulate(
        TrueCart.from_values(values, v_band=NARROW), ex.step(pid, amplitude, horizon=1.2), NONE
    )
    assert np.max(np.abs(np.asarray(ref.position) - run.position)) < 2e-7
    assert np.max(np.abs(np.asarray(ref.command) - run.command)) < 1e-4


def test_a_coasting_tap_agrees_with_jaxcarts_exact_simulator():
    """The same coast from the state after the push, motor unplugged (1e-9 m)."""
    cart = TrueCart(B_eq=1.5, f_c=0.4, v_band=NARROW)
    run = simulate(cart, ex.tap(speed=0.6, rest=0.0, horizon=1.0), NONE)
    k0 = int(math.ceil(run.push[1] / TS)) + 1
    plant = jc.build_plant({"B_eq": 1.5, "f_c": 0.4}, motor_connected=False)
    coast = jc.tap(float(run.velocity[k0]), horizon=run.time[-1] - run.time[k0],
                   y0=float(run.true_position[k0]))  # fmt: skip
    ref = jc.simulate(plant, None, coast, solver=jc.Exact())
    assert np.max(np.abs(np.asarray(ref.position) - run.true_position[k0:])) < 1e-9


def test_a_recording_reads_back_as_a_users_file(tmp_path):
    """Realistic artefacts: whole counts from a reading of 0, the file's clock k Ts, the
    controller that ran, the command replayed by the lab's law on the counts it read (the
    controller read the encoder), and the truth in [notes]."""
    cart = TrueCart(B_eq=4.6, f_c=0.3, v_sat=5.0, f_c_neg=0.35)
    pid = jc.PID(kp=40.0, kd=3.0, v_limit=6.0)
    rec = make_recording(cart, ex.square(pid, 0.1, period=0.6, horizon=0.6), tmp_path / "sq.toml",
                         seed=4)  # fmt: skip
    back = read_experiment(rec.path)
    q = REALISTIC.quantization
    counts = back.position / q
    assert back.kind == "closed_loop" and back.controller == pid
    assert back.position[0] == 0.0 and np.max(np.abs(counts - np.round(counts))) < 1e-6
    assert np.array_equal(back.time, np.arange(601) * TS)
    assert np.any(rec.run.instants != back.time)  # the samples were taken off the clock
    state, replay = pid_init(pid, back.reference[0], back.position[0]), []
    for rk, yk in zip(back.reference, back.position, strict=True):
        u, _, state = pid_update(pid, state, rk, yk)
        replay.append(float(u))
    assert np.max(np.abs(np.array(replay) - back.command)) < 1e-12
    notes = back.meta["notes"]
    assert notes["truth_f_c_neg"] == 0.35 and notes["artefact_jitter"] == REALISTIC.jitter


def test_a_run_draws_its_own_drive_within_the_spread():
    """Runs of one cart: each draws its drive gain and limits (clipped at 2.5 sigma); turning
    the jitter off leaves the other draws as they were."""
    cart = TrueCart(B_eq=4.6, v_sat=5.0, i_max=2.0)
    e = ex.voltage_step(1.0, horizon=0.05)
    runs = [simulate(cart, e, REALISTIC, seed=s) for s in range(6)]
    gains = [r.truth.gamma_scale for r in runs]
    assert len(set(gains)) == 6 and max(abs(g - 1.0) for g in gains) <= 2.5 * 0.01 + 1e-12
    assert all(abs(r.truth.v_sat / r.truth.i_max - 2.5) < 1e-12 for r in runs)  # one draw
    quiet = simulate(cart, e, REALISTIC.replace(jitter=0.0), seed=0)
    assert quiet.truth == runs[0].truth and np.all(quiet.instants == quiet.time)


def test_run_controller_gives_the_metrics_of_jaxcart_on_the_linear_cart(tmp_path):
    """A gains file on the linear cart: the step metrics (docs/design.md "Metrics") as
    jaxcart.step_info gives them for jaxcart's own run (to a sample, and 1e-6 %)."""
    pid = jc.PID(kp=80.0, kd=8.0, ki=2.0, v_limit=6.0)
    path = write_gains(tmp_path / "gains.json", pid)
    got = run_controller(TrueCart(B_eq=4.6), path, amplitude=0.5, horizon=2.0)
    ref = jc.step_info(jc.simulate(jc.handout_plant(B_eq=4.6), pid, jc.step(0.5, horizon=2.0),
                                   solver=jc.Exact()), v_limit=6.0)  # fmt: skip
    m = got.metrics
    assert abs(m.settling_time - ref.settling_time) <= TS + 1e-12
    assert abs(m.rise_time - ref.rise_time) <= TS + 1e-12
    assert abs(m.overshoot - ref.overshoot) < 1e-6
    assert m.peak_command == pytest.approx(6.0) and m.meets() and ref.meets()


def test_the_generator_shares_no_simulation_code_with_jaxcart():
    """tuning/verification imports none of jaxcart's simulators, effects or synthetic
    recordings, and none of hw.control_law's stepping (its PID is a settings record there)."""
    import ast
    from pathlib import Path

    banned = ("jaxcart.exact", "jaxcart.smooth_sim", "jaxcart.effects", "jaxcart.synthetic",
              "jaxcart.simulation", "jaxcart.chunked_sim")  # fmt: skip
    folder = Path(__file__).resolve().parent.parent / "tuning" / "verification"
    for path in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [(a.name, None) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [(node.module or "", a.name) for a in node.names]
            else:
                continue
            for module, name in names:
                assert not module.startswith(banned), f"{path.name} imports {module}"
                assert not (module == "hw.control_law" and name != "PID"), f"{path.name}: {name}"


def test_the_suite_makes_its_cases_on_the_independent_generator(tmp_path):
    """Several runs of one cart: each run draws its own drive limit (what the per-run rule is
    judged against); a case of one drive limit keeps it; one recording keeps the cart's own."""
    from tuning.estimation.diagnose.suite import CASES, make_recordings

    by_name = {c.name: c for c in CASES}
    varied = make_recordings(
        by_name["tap + P and PD steps with the drive limit per run"], tmp_path / "a", "independent"
    )
    assert [read_experiment(p).kind for p, _ in varied] == ["tap", "closed_loop", "closed_loop"]
    limits = [truth["v_sat"] for _, truth in varied[1:]]
    assert limits[0] != 4.6 and limits[1] != 5.5
    assert abs(limits[0] / 4.6 - 1) < 0.08 and abs(limits[1] / 5.5 - 1) < 0.08
    shared = make_recordings(
        by_name["tap + two P steps with one drive limit"], tmp_path / "b", "independent"
    )
    assert [truth["v_sat"] for _, truth in shared[1:]] == [5.0, 5.0]
    ((_, alone),) = make_recordings(by_name["saturation plain"], tmp_path / "c", "independent")
    assert alone["v_sat"] == 4.0 and "gamma_scale" not in alone


def test_the_drive_freed_per_run_is_no_false_alarm_where_the_runs_truths_differ():
    """A cart whose runs drew their own current limit: freeing it per run is right; had their
    truths shared one limit, it would be a false alarm."""
    from tuning.estimation.diagnose.result import Diagnosis
    from tuning.estimation.diagnose.structures import PER_RUN, Candidate
    from tuning.estimation.diagnose.suite import CASES, judge

    name = "one cart (tap + P 50 + PD): current limit 1.2 A"
    case = {c.name: c for c in CASES}[name].on("independent")
    parts = ("coulomb", "current_limit", PER_RUN)
    d = Diagnosis(["a"], "diagnosed", [], [], rms_before=1e-3, rms_after=1e-5,
                  left_out=["coulomb", "current_limit"])  # fmt: skip
    d.candidates = [Candidate("+".join(parts), parts, ("B_eq",))]
    d.chosen = d.candidates[0].name
    tap = {"motor_connected": False, "i_max": 1.2}
    row = judge(case, d, [tap, {"i_max": 1.23}, {"i_max": 1.18}])
    assert row["correct"] and not row["false_alarm"]
    assert judge(case, d, [tap, {"i_max": 1.2}, {"i_max": 1.2}])["false_alarm"]
