"""Physical sense of recordings and controllers (jaxcart.plausibility), outputs checked before a
run (jaxcart.outputs.check_writable) and long runs (jaxcart.chunked_sim)."""

import dataclasses
import io
import shutil
from pathlib import Path

import control
import jax
import numpy as np
import pytest

import jaxcart as jc
from jaxcart import chunked_sim, plausibility
from jaxcart.errors import UserError
from jaxcart.files import read_experiment
from jaxcart.outputs import check_writable

DATA = Path(jc.__file__).parent / "data"
#: Eigenvalues of the closed loop against python-control's (a 4th-order loop with roots near
#: z = 1; both are eigenvalues of well-scaled matrices).
EIG_TOL = 1e-9
#: The chunked run repeats the same steps as one scan: the same floats up to XLA's fusion.
CHUNKED_TOL = 1e-12

simulate = jax.jit(jc.simulate)


def _copy(tmp_path, name):
    for suffix in (".toml", ".csv"):
        shutil.copy(DATA / f"{name}{suffix}", tmp_path / f"{name}{suffix}")
    return tmp_path / f"{name}.toml"


def _scale_column(path, column, factor):
    text = path.read_text().splitlines()
    header = text[0].split(",")
    i = header.index(column)
    rows = [line.split(",") for line in text[1:]]
    for row in rows:
        row[i] = repr(float(row[i]) * factor)
    path.write_text("\n".join([text[0]] + [",".join(r) for r in rows]) + "\n")


# ---------------------------------------------------------------- controllers


def _control_poles(pid, plant):
    """Poles of the same loop built with python-control: the plant discretized by its c2d
    (zero-order hold), the PID as its transfer function in z, unity feedback."""
    ts = pid.sample_time
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    cart = control.ss([[0, 1], [0, -c / m]], [[0], [gamma / m]], [[1, 0]], [[0]])
    cart_d = control.c2d(cart, ts, method="zoh")
    z = control.tf([1, 0], [1], ts)
    law = pid.kp + pid.ki * ts / (z - 1) + pid.kd * (z - 1) / ((pid.tau + ts) * z - pid.tau)
    loop = control.feedback(control.tf2ss(law) * cart_d, 1)
    return np.sort_complex(np.linalg.eigvals(loop.A))


@pytest.mark.parametrize(
    "gains",
    [
        dict(kp=40.0, kd=5.0, ki=5.0),
        dict(kp=250.0, kd=15.0, ki=30.0),
        dict(kp=-100.0, ki=1.0, kd=0.5),
    ],
)
def test_closed_loop_eigenvalues_match_python_control(gains):
    pid, plant = jc.PID(v_limit=6.0, **gains), jc.handout_plant(B_eq=4.6)
    ours = plausibility.closed_loop_eigenvalues(pid, plant)
    # Our 5-state form carries s_{k-1} and d_{k-1}: one extra eigenvalue at 0.
    ours = np.sort_complex(np.delete(ours, np.argmin(np.abs(ours))))
    np.testing.assert_allclose(ours, _control_poles(pid, plant), rtol=0, atol=EIG_TOL)


def test_unstable_and_implausible_controllers_are_flagged_lab_gains_are_not():
    plant = jc.handout_plant()
    for gains in (dict(kp=40.0, kd=5.0, ki=5.0), dict(kp=100.0, kd=6.0), dict(kp=250.0, kd=15.0)):
        assert plausibility.check_controller(jc.PID(v_limit=6.0, **gains), plant) == []
    negative, unstable = plausibility.check_controller(jc.PID(kp=-100.0, v_limit=6.0), plant)
    assert "kp = -100.0 V/m" in negative and "sign error" in negative
    assert "unstable" in unstable and "kp=-100" in unstable and "|z| = 1.0" in unstable
    # The eigenvalue says what a simulation of the linear loop (no limit) shows: growth.
    res = simulate(plant, jc.PID(kp=-100.0), jc.step(0.01, horizon=3.0))  # shares a compile
    z = np.max(np.abs(plausibility.closed_loop_eigenvalues(jc.PID(kp=-100.0), plant)))
    y = np.abs(np.asarray(res.position))
    growth = (y[1000] / y[800]) ** (1 / 200)  # per sample, once the unstable mode dominates
    assert abs(growth - z) < 1e-4
    big = plausibility.check_controller(jc.PID(kp=1e6, v_limit=6.0), plant)
    assert any("implausible" in m and "encoder count" in m and "relay" in m for m in big)
    fast = plausibility.check_controller(jc.PID(kp=200.0, kd=3000.0, tau=0.0), plant)
    assert any("kd=3000" in m and "implausible" in m for m in fast)


#: Gains the delay-free loop holds (|z| < 1) and a transport delay of 5.92 ms destabilizes
#: (between whole samples: 5 ms holds, 6 ms does not, so only the split sample tells 5.85 ms
#: from 5.95 ms). Plausible by every other check (kp q = 0.05 V).
DELAYED_PID = jc.PID(kp=2000.0, kd=10.0, ki=10.0)
#: The oscillatory mode of an exact simulation (|z| per sample and its angle [rad]) against
#: the loop's pole pair: a two-term recurrence fitted by least squares to y's second
#: differences once the other modes have died out (measured agreement 7e-13 or better).
MODE_TOL = 1e-9


def _delayed(delay):
    return jc.build_plant({"delay": delay})


@pytest.mark.parametrize("delay", [0.0005, 0.003, 0.005, 0.00585, 0.00595, 0.0075, 0.02])
@pytest.mark.parametrize(
    "gains", [dict(kp=40.0, kd=5.0, ki=5.0), dict(kp=2000.0, kd=10.0, ki=10.0)]
)
def test_delayed_loop_eigenvalues_are_the_control_systems_poles(delay, gains):
    """With a delay effect the loop matrix gains one state per held command; its eigenvalues
    are the poles of jaxcart.control_systems' python-control loop (cart behind the delay line
    by scipy's matrix exponential) plus the one at 0 of s_{k-1}, to EIG_TOL."""
    from jaxcart import control_systems as cs

    pid, plant = jc.PID(**gains), _delayed(delay)
    rest = list(plausibility.closed_loop_eigenvalues(pid, plant))
    poles = cs.closed_loop_poles(plant, pid)
    assert len(rest) == len(poles) + 1
    for pole in poles:
        nearest = min(range(len(rest)), key=lambda i: abs(rest[i] - pole))
        assert abs(rest.pop(nearest) - pole) < EIG_TOL
    assert abs(rest[0]) < EIG_TOL


@pytest.mark.parametrize(
    "delay, unstable",
    [
        (0.0045, False),
        (0.005, False),
        (0.00585, False),
        (0.00595, True),
        (0.006, True),
        (0.007, True),
        (0.0075, True),
    ],
)
def test_a_loop_that_a_delay_destabilizes_is_reported(delay, unstable):
    """The verdict and the mode against the exact simulator (numpy, the delay effect's exact
    form) of the linear loop: the oscillation of the simulated run has the loop's oscillatory
    pole pair, to MODE_TOL, and grows (|z| > 1) exactly when the check reports instability."""
    from jaxcart.exact import simulate_exact

    plant = _delayed(delay)
    pid = jc.PID(kp=DELAYED_PID.kp, kd=DELAYED_PID.kd, ki=DELAYED_PID.ki, v_limit=6.0)
    assert plausibility.check_controller(pid, jc.handout_plant()) == []  # fine without delay
    messages = plausibility.check_controller(pid, plant)
    if unstable:
        (message,) = messages
        assert "unstable" in message and f"{delay * 1e3:g} ms delay" in message
    else:
        assert messages == []
    z = plausibility.closed_loop_eigenvalues(DELAYED_PID, plant)
    osc = z[np.abs(z.imag) > 1e-9]
    pole = osc[np.argmax(np.abs(osc))]
    res = simulate_exact(plant, DELAYED_PID, jc.step(0.001, horizon=4.0))  # no limit: linear
    # From sample 2000 on only the slowest modes are left: a real pole near 1, which the
    # second difference removes, and the oscillatory pair: x_{k+1} = 2 r cos(th) x_k - r^2 x_{k-1}.
    x = np.diff(np.asarray(res.position), 2)[2000:]
    (a, b), *_ = np.linalg.lstsq(np.stack([x[1:-1], x[:-2]], 1), x[2:], rcond=None)
    r = np.sqrt(-b)
    assert abs(r - abs(pole)) < MODE_TOL
    assert abs(np.arccos(a / (2 * r)) - abs(np.angle(pole))) < MODE_TOL
    assert (r > 1) == unstable and (
        np.max(np.abs(z)) > 1 + plausibility.UNIT_CIRCLE_TOL
    ) == unstable


def test_no_delay_and_a_zero_delay_give_the_delay_free_loop():
    pid = jc.PID(kp=40.0, kd=5.0, ki=5.0)
    free = plausibility.closed_loop_matrix(pid, jc.handout_plant())
    assert free.shape == (5, 5)
    np.testing.assert_array_equal(plausibility.closed_loop_matrix(pid, _delayed(0.0)), free)
    np.testing.assert_array_equal(
        plausibility.closed_loop_matrix(pid, _delayed(0.004), with_delay=False), free
    )
    assert plausibility.closed_loop_matrix(pid, _delayed(0.004)).shape == (9, 9)  # u_1..u_4
    assert plausibility.closed_loop_matrix(pid, _delayed(0.0045)).shape == (10, 10)  # + split
    assert plausibility.delay_split(0.0045, 0.001) == (4, pytest.approx(0.0005, abs=1e-15))


def test_a_long_delay_does_not_make_lab_gains_implausible():
    """A 20 ms delay line has poles of |z| ~ 0.7 at every angle: the fast-mode check judges the
    gains on the loop without it, so the lab's gains stay clean (and stable)."""
    for gains in (dict(kp=40.0, kd=5.0, ki=5.0), dict(kp=250.0, kd=15.0, ki=30.0)):
        assert plausibility.check_controller(jc.PID(v_limit=6.0, **gains), _delayed(0.02)) == []


# ---------------------------------------------------------------- recordings


def test_built_in_and_real_recordings_read_without_warnings(realdata, capsys):
    names = [p for p in DATA.glob("*.toml") if p.name != "lab.toml"]
    for path in names + sorted(Path(realdata).glob("*.toml")):
        rec = read_experiment(path)
        assert rec.warnings == (), (path, rec.warnings)
    assert "warning" not in capsys.readouterr().err


def test_positions_in_mm_are_one_line_errors(tmp_path):
    path = _copy(tmp_path, "tap")
    _scale_column(tmp_path / "tap.csv", "y", 1000.0)
    with pytest.raises(UserError) as err:
        read_experiment(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and "column y" in msg
    assert "recorded in mm? divide by 1000" in msg and "0.99 m track" in msg
    # In cm: the message names cm.
    _scale_column(tmp_path / "tap.csv", "y", 0.1)
    with pytest.raises(UserError, match=r"recorded in cm \(or mm\)\? divide by 100"):
        read_experiment(path)


def test_motion_beyond_the_cart_and_a_fast_clock_are_warnings(tmp_path, capsys):
    path = _copy(tmp_path, "tap")
    _scale_column(tmp_path / "tap.csv", "t", 0.1)
    path.write_text(path.read_text().replace("sample_time = 0.001", "sample_time = 0.0001"))
    rec = read_experiment(path)
    (warning,) = rec.warnings
    # A tap coasts to rest within the travel: v(0) <= travel c / m (unplugged: c = B_eq).
    plant = rec.plant()
    limit = 0.814 * float(plant.c) / float(plant.m)
    assert "velocity up to" in warning and f"{limit:.3g} m/s" in warning
    err = capsys.readouterr().err
    assert err.count("warning:") == 1
    read_experiment(path)  # printed once per process
    assert "warning" not in capsys.readouterr().err
    slow = _copy(tmp_path, "p10")
    _scale_column(tmp_path / "p10.csv", "t", 100.0)
    slow.write_text(slow.read_text().replace("sample_time = 0.001", "sample_time = 0.1"))
    assert any("time recorded in ms" in w for w in read_experiment(slow).warnings)


def test_recorded_command_checked_against_the_files_controller(tmp_path):
    path = _copy(tmp_path, "p50")
    assert read_experiment(path).warnings == ()
    rec = read_experiment(path)
    # The vectorized command is the canonical control law's, sample by sample.
    from hw.control_law import float_pid, pid_init, pid_update

    pid = float_pid(jc.PID(kp=50.0, kd=2.0, ki=3.0, v_limit=6.0))
    state, ref = pid_init(pid, rec.reference[0], rec.position[0]), []
    for r, y in zip(rec.reference, rec.position, strict=True):
        u, _, state = pid_update(pid, state, r, y)
        ref.append(u)
    ours = plausibility.controller_command(pid, rec.reference, rec.position)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9)
    path.write_text(path.read_text().replace("kp = 50.0", "kp = 80.0"))
    (warning,) = read_experiment(path).warnings
    assert "recorded u is not what kp=80" in warning and "wrong gains" in warning
    path.write_text(path.read_text().replace("kp = 80.0", "kp = 50.0"))
    _scale_column(tmp_path / "p50.csv", "v", 1000.0)  # v in mV
    (warning,) = read_experiment(path).warnings
    assert "about 1e+03 times" in warning
    _scale_column(tmp_path / "p50.csv", "v", -0.001)  # back in V, of the other sign
    (warning,) = read_experiment(path).warnings
    assert "about -1 times it, of the opposite sign" in warning
    assert "distance from the far end?" in warning


def test_simulated_cart_leaving_the_track_is_flagged():
    res = simulate(jc.handout_plant(), jc.PID(kp=-100.0, v_limit=6.0), jc.step(0.5, horizon=3.0))
    (warning,) = plausibility.check_track(res, "run")
    assert "leaves the track" in warning and "0.814 m travel" in warning
    ok = simulate(jc.handout_plant(), jc.PID(kp=40.0, kd=5.0, v_limit=6.0), jc.step(0.5))
    assert plausibility.check_track(ok, "run") == []


# ---------------------------------------------------------------- outputs


def test_check_writable(tmp_path):
    (tmp_path / "file").write_text("x")
    assert check_writable(tmp_path / "new" / "a.csv", suffixes=(".csv",)) == tmp_path / "new/a.csv"
    cases = [
        (tmp_path / "file" / "a.csv", "is a file, so nothing can be written under it"),
        (tmp_path / "a.txt", "unknown suffix '.txt'; give a name ending in .csv"),
        (tmp_path, "is a folder"),
    ]
    for path, expected in cases:
        with pytest.raises(UserError, match=expected) as err:
            check_writable(path, suffixes=(".csv",), option="--out")
        assert str(err.value).startswith(f"--out {path}") and "\n" not in str(err.value)
    (tmp_path / "old.csv").write_text("mine")
    with pytest.raises(UserError, match="exists; choose another name or pass --force"):
        check_writable(tmp_path / "old.csv", force=False)
    assert (tmp_path / "old.csv").read_text() == "mine"
    ro = Path("/proc/jaxcart-test/a.csv")  # a file system nobody writes to, root included
    if Path("/proc").is_dir():
        with pytest.raises(UserError, match="not writable"):
            check_writable(ro)


# ---------------------------------------------------------------- long runs


def test_chunked_run_is_the_same_run_and_reports_progress():
    plant, pid = jc.handout_plant(), jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
    exp = jc.step(0.5, horizon=3.0)  # the compile of the other tests' runs
    out = io.StringIO()
    chunked = chunked_sim.simulate_chunked(plant, pid, exp, chunk=1024, out=out)
    whole = simulate(plant, pid, exp)
    for field in ("position", "velocity", "command", "voltage", "error"):
        np.testing.assert_allclose(
            getattr(chunked, field), np.asarray(getattr(whole, field)), rtol=0, atol=CHUNKED_TOL
        )
    assert "simulate: 100% (3001 of 3001 samples" in out.getvalue()
    assert (
        chunked_sim.announce(100.0, 10**8, 5, 0.001, out)
        and "--horizon to shorten" in out.getvalue()
    )
    assert not chunked_sim.announce(1.0, 100, 5, 0.001, out)


def test_long_runs_refused_before_they_start(monkeypatch):
    monkeypatch.setattr(chunked_sim, "memory_budget", lambda: 1e6)
    with pytest.raises(UserError, match=r"--horizon 100: 1e\+05 samples need about 12.8 MB"):
        chunked_sim.check_size(100_001, 0.001, "--horizon 100")


def test_thinned_curves_keep_their_envelope():
    rng = np.random.default_rng(1)
    y = np.cumsum(rng.normal(size=100_000))
    v = rng.normal(size=y.size)
    keep = chunked_sim.thin_indices(y.size, y, v, points=2000)
    assert keep.size <= 2100 and keep[0] == 0 and keep[-1] == y.size - 1
    assert y[keep].max() == y.max() and y[keep].min() == y.min() and v[keep].max() == v.max()


def test_slow_derivative_filter_by_fft_is_the_control_law(monkeypatch):
    """A slow derivative filter (tau = 0.5 s: a long kernel) goes by FFT; it still is the
    canonical control law's command, sample by sample."""
    from hw.control_law import float_pid, pid_init, pid_update

    monkeypatch.setattr(plausibility, "DIRECT_CONVOLUTION_LIMIT", 0)
    rng = np.random.default_rng(3)
    n = 4000
    r = np.where(np.arange(n) > 100, 0.3, 0.0)
    y = np.cumsum(rng.normal(0, 1e-4, n))
    pid = float_pid(jc.PID(kp=40.0, kd=3.0, ki=2.0, tau=0.5, v_limit=1e9))
    state, ref = pid_init(pid, r[0], y[0]), []
    for rk, yk in zip(r, y, strict=True):
        u, _, state = pid_update(pid, state, rk, yk)
        ref.append(u)
    ours = plausibility.controller_command(pid, r, y)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9)


# ---------------------------------------------------------------- before a fit (issue 23 item 3)

#: The nominal linear cart of the input-units check against the exact simulator on a plant
#: without effects: both are the exact zero-order-hold solution, so only rounding differs [m].
LINEAR_TOL = 1e-12


def _open_loop(volts, *, horizon=0.3, seed=0):
    from jaxcart.synthetic import make_recording

    u = np.full(int(round(horizon / 0.001)) + 1, volts)
    return make_recording(jc.handout_plant(), None, jc.voltage_sequence(u), seed=seed)


def test_the_units_check_models_the_cart_as_the_exact_simulator_does():
    from jaxcart.exact import simulate_exact

    plant = jc.handout_plant()
    u = 2.0 * np.sin(np.arange(400) * 0.02)
    reference = simulate_exact(plant, None, jc.voltage_sequence(u))
    mine = plausibility._linear_response(plant, 0.001, u)
    np.testing.assert_allclose(mine, np.asarray(reference.position), rtol=0, atol=LINEAR_TOL)


def test_an_open_loop_input_in_mv_is_refused_and_one_in_volts_passes():
    rec = _open_loop(2.0)
    assert plausibility.check_input_units(rec) == []  # the cart moves as 2 V move it
    in_mv = dataclasses.replace(rec, signal=rec.signal64() * 1000)
    with pytest.raises(UserError, match=r"2000 V.*recorded in mV\? divide by 1000"):
        plausibility.check_input_units(in_mv)
    # 20 V (in range) where 0.3 V moved the cart: a warning with the same fix.
    weak = dataclasses.replace(_open_loop(0.02), signal=np.full(301, 20.0))
    (message,) = plausibility.check_input_units(weak)
    assert "v in mV (divide by 1000)" in message


def test_fit_refuses_a_still_cart_and_the_same_data_twice_before_fitting():
    from tuning.estimation.fit import fit

    rec = _open_loop(2.0)
    still = dataclasses.replace(rec, position=np.zeros_like(rec.position))
    with pytest.raises(UserError, match="the cart does not move: y spans 0 mm"):
        fit([still], ("B_eq",), progress=False)
    with pytest.raises(UserError, match="recordings 1 and 3 are identical samples"):
        fit([rec, _open_loop(1.0), rec], ("B_eq",), progress=False)
    # Another seed is other data: both pass (the check alone, no fitting here).
    assert len(plausibility.check_fit_recordings([rec, _open_loop(2.0, seed=1)])) == 2


def _rows_written(folder: Path, rec, rows, kind: str, extra: str = "") -> Path:
    """Rows ``rows`` of ``rec`` (t, y, and v where it has one) as a CSV experiment file of
    ``kind``, its TOML ending with ``extra`` (a controller and a reference)."""
    folder.mkdir()
    cols = {"t": rec.time, "y": rec.position}
    if rec.command is not None:
        cols["v"] = rec.command
    data = np.column_stack([np.asarray(c, dtype=float)[rows] for c in cols.values()])
    header = ",".join(cols)
    np.savetxt(folder / "run.csv", data, delimiter=",", header=header, comments="", fmt="%.17g")
    toml = f'kind = "{kind}"\nsample_time = 0.001\ndata = "run.csv"\n{extra}'
    (folder / "run.toml").write_text(toml)
    return folder / "run.toml"


def test_a_run_recorded_late_and_a_tap_cut_while_coasting_are_warned(tmp_path, realdata):
    """The real P 50 step with its first 100 ms dropped starts with the cart at 0.575 m/s,
    where every simulation starts it at rest (fitted so, B_eq came out 1.44 for the whole
    run's 4.2, and a diagnosis named a spring and an extra 0.76 kg); the real tap cut at 60 %
    of its samples ends with the cart still coasting at 0.55 m/s, without the stop that tells
    f_c from B_eq (f_c 0.135 +/- 0.052 N for the whole tap's 0.437). Each is warned; the
    whole recordings are not (above)."""
    p50 = read_experiment(Path(realdata) / "p50.toml")
    p50_head = (
        '[controller]\nkp = 50.0\nv_limit = 6.0\n[reference]\nkind = "step"\namplitude = 0.4\n'
    )
    late = _rows_written(tmp_path / "late", p50, slice(100, None), "closed_loop", p50_head)
    (warning,) = [w for w in read_experiment(late).warnings if "first sample" in w]
    assert "moves at 0.57" in warning and "started after the run did" in warning
    tap = read_experiment(Path(realdata) / "tap.toml")
    cut = _rows_written(tmp_path / "cut", tap, slice(0, int(0.6 * tap.position.size)), "tap")
    (warning,) = [w for w in read_experiment(cut).warnings if "last sample" in w]
    assert "still moves at 0.5" in warning and "cut before the cart came to rest" in warning


def test_a_run_under_integral_action_whose_clock_starts_late_is_warned(tmp_path):
    """A scope that kept only a run's last samples (the students' Part (iv) error scope saved
    from t = 15 s) starts where the PI's integral had built up, which the simulations start
    at 0: the cart may be at rest there, so only the clock tells. Warned for PI, not for the
    same file under P control, nor for a PI run recorded from t = 0."""
    t = 15.0 + 1e-3 * np.arange(2000)
    y = np.where(t > 15.5, 0.3957 + 2e-5 * (t - 15.5), 0.3957)
    y = np.round(y / 2.2735e-5) * 2.2735e-5
    head = 'kind = "closed_loop"\nsample_time = 0.001\ndata = "run.csv"\n'
    ref = '[reference]\nkind = "step"\namplitude = 0.4\n'

    def warned(start, controller):
        folder = tmp_path / f"{start}-{controller.count('ki')}"
        folder.mkdir()
        np.savetxt(folder / "run.csv", np.column_stack([t - 15.0 + start, y]), delimiter=",",
                   header="t,y", comments="", fmt="%.17g")  # fmt: skip
        (folder / "run.toml").write_text(head + controller + ref)
        return [w for w in read_experiment(folder / "run.toml").warnings if "integral" in w]

    pi, p = "[controller]\nkp = 10.0\nki = 15.0\n", "[controller]\nkp = 10.0\n"
    (warning,) = warned(15.0, pi)
    assert "run.csv column t: the time starts at t = 15 s" in warning
    assert "ki = 15 V/(m s)" in warning and "record the run from its step" in warning
    assert warned(15.0, p) == [] and warned(0.0, pi) == []
