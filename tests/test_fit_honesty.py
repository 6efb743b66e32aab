"""What a fit says about itself (tuning/estimation/fit.py): a model that does not explain the data
is
flagged and its standard errors widened to what the residual supports; an optimizer stopped at
its cap says so; outputs are checked before any fitting; the batched Levenberg-Marquardt
evaluates K trial points as K single runs would, without recompiling. References: the encoder's
q / sqrt(12) and the white noise against the recording's own true positions, and the AR(1)
integrated autocorrelation time (1 + rho) / (1 - rho)."""

import math

import jax
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.synthetic import make_recording, write_recording
from tuning.estimation import fit
from tuning.estimation.engine import smooth_runs
from tuning.estimation.engine.noise import MISFIT_RATIO, effective_samples, floor_of
from tuning.estimation.fitting import model

Q = jc.ENCODER_RESOLUTION
TRUTH = {"B_eq": 3.0, "f_c": 0.5}
#: One width and few iterations: these tests check what a fit reports, not its accuracy
#: (tests/test_fit.py does that with the default settings).
QUICK = fit.FitSettings(widths=(1e-3, 1e-4), adam_steps=0)


@pytest.fixture(scope="module")
def tap():
    truth = jc.tap_plant(B_eq=TRUTH["B_eq"], effects=(jc.Coulomb(f_c=TRUTH["f_c"]),))
    return make_recording(truth, None, jc.tap(1.0, horizon=0.6), seed=0)


@pytest.fixture(scope="module")
def good(tap):
    return fit.fit([tap], ("B_eq", "f_c"), settings=QUICK, progress=False)


def test_a_correct_model_is_not_flagged(good):
    assert good.rms_after_exact < 1.3 * Q / math.sqrt(12)
    assert good.misfit == "" and good.converged and good.warnings == []
    doc = good.to_json()
    assert doc["model_explains_data"] is True and doc["converged"] is True
    assert good.rms_after_exact < MISFIT_RATIO * doc["noise_floor"]
    for name, e in good.params.items():  # the HAC error, not widened
        assert abs(e.value - TRUTH[name]) < 3 * e.stderr


def test_a_missing_effect_is_flagged_and_its_errors_widened(tap, good):
    # Coulomb friction left out: B_eq alone cannot explain the coast.
    bad = fit.fit([tap], ("B_eq",), settings=QUICK, progress=False)
    b = bad.params["B_eq"]
    assert bad.rms_after_exact > 10 * bad.noise_floor
    assert "does not explain the data" in bad.misfit and bad.misfit in bad.warnings
    assert bad.to_json()["model_explains_data"] is False
    # Widened to what n_eff independent samples support: sigma (J^T J)^-1/2 sqrt(N / n_eff).
    assert 1 <= bad.n_effective < bad.n_data / 5
    assert b.stderr >= b.stderr_naive * math.sqrt(bad.n_data / bad.n_effective) * (1 - 1e-9)
    # The interval covers the truth, or the fit is flagged (it is, above); print what it is.
    z = (b.value - TRUTH["B_eq"]) / b.stderr
    print(f"\nmisfit: B_eq = {b.value:.4g} +/- {b.stderr:.2g} kg/s (truth 3), z = {z:+.1f}")
    table = fit.fit_table(bad)
    assert table["model_explains_data"] is False and table["warnings"] == bad.warnings


def test_an_optimizer_at_its_cap_says_so(tap, good):
    layout_traces = dict(model.TRACES)
    capped = fit.fit(
        [tap],
        ("B_eq", "f_c"),
        settings=fit.FitSettings(widths=(1e-2,), adam_steps=0, lm_iterations=1),
        exact=False,
        progress=False,
    )
    assert not capped.converged and capped.to_json()["converged"] is False
    stage = capped.stages[0]
    assert stage["iterations"] == stage["cap"] == 1 and not stage["converged"]
    assert any("stopped at its iteration cap (1)" in w for w in capped.warnings)
    assert fit.fit_table(capped)["converged"] is False
    # Same recording and parameters, another width and cap: the compiled program is reused.
    assert model.TRACES == layout_traces


def test_batched_trials_equal_single_runs(tap):
    seg = fit.fit_segment(tap, ("B_eq", "f_c"), {}, QUICK)
    problem = model._Problem([seg], ("B_eq", "f_c"), QUICK)
    points = problem.theta0 + np.array([[0.0, 0.0, 0.0, 0.0], [0.1, -0.2, 0.5, 0.3]])
    r_k, j_k = problem.evaluate_batch(points, 1e-3)
    for k, theta in enumerate(points):
        r, jac = problem.evaluate(theta, 1e-3)
        np.testing.assert_allclose(r_k[k], r, rtol=0, atol=1e-12)
        np.testing.assert_allclose(j_k[k], jac, rtol=1e-10, atol=1e-12)
    assert not np.allclose(r_k[0], r_k[1])


def test_side_by_side_runs_equal_runs_apart(tap):
    """The engine's one smooth simulation of recordings (smooth_runs.positions): two
    recordings alike in everything static run as lanes of one loop (a diagnosis's way) give
    what they give each in its own loop (a fit's), to 1e-12 m; each lane is its own run (the
    second's start moved by 1 mm moves its positions, not the first's)."""
    seg = fit.fit_segment(tap, ("B_eq", "f_c"), {}, QUICK)
    problem = model._Problem([seg, seg], ("B_eq", "f_c"), QUICK)
    plants, ctrls, exps, bases = (list(x) for x in zip(*problem.data, strict=True))
    theta = problem.theta0.copy()
    theta[problem.layout.starts[1][0][1]] += 1.0  # y0 of the second: +1 mm (its scale)
    with jax.enable_x64(True):
        full = model._full(theta, bases, problem.static)
        smoothing = problem.smoothing(1e-3)
        apart = problem.static.shape
        assert len(apart.groups) == 2
        together = apart._replace(groups=((0, 1),))
        a = smooth_runs.positions(plants, ctrls, exps, full, problem.layout, smoothing, apart)
        b = smooth_runs.positions(plants, ctrls, exps, full, problem.layout, smoothing, together)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-12)
    # No force depends on the position: the second run is the first moved by 1 mm.
    np.testing.assert_allclose(np.asarray(a[1]) - np.asarray(a[0]), 1e-3, rtol=0, atol=1e-12)


def test_noise_floor_against_the_true_positions():
    truth = jc.handout_plant(B_eq=2.5, f_c=0.3)
    for noise in (0.0, 2e-5):
        rec = make_recording(truth, jc.PID(kp=20.0), jc.ramp(0.2, horizon=2.0), seed=4, noise=noise)
        seg = fit.fit_segment(rec, ("B_eq",), {}, fit.FitSettings())
        # About its mean: a constant offset (the count's phase in noisy data) is y0's part.
        err = seg.target - rec.true_position
        assert floor_of([seg]) == pytest.approx(np.std(err), rel=0.1), noise


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_effective_samples_of_an_ar1_series(rho):
    rng = np.random.default_rng(3)
    n = 100_000
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0]
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    tau = (1 + rho) / (1 - rho)
    assert effective_samples([x]) == pytest.approx(n / tau, rel=0.1)
    assert effective_samples([np.ones(500)]) < 2  # a bias is one observation


def test_outputs_are_checked_before_fitting(tmp_path, tap, capsys):
    from tuning.commands.main import main

    toml = write_recording(tap, tmp_path / "tap.toml")
    (tmp_path / "file.txt").write_text("a regular file")
    for option, name in (("--out", "x.toml"), ("--json", "x.json"), ("--plot", "x.png")):
        bad = tmp_path / "file.txt" / name
        assert main(["fit", str(toml), option, str(bad)]) == 2
        err = capsys.readouterr().err
        assert "is a file" in err and option in err and len(err.strip().splitlines()) == 1
        assert not any(line.startswith("fit:") for line in err.splitlines())  # not started
    assert main(["fit", str(toml), "--plot", str(tmp_path / "fit.xyz")]) == 2
    assert ".png" in capsys.readouterr().err


# ---------------------------------------------------------------- edges and late steps


def _late_p50(folder, *, late_s=1.0, with_v=True):
    """The built-in P 50 recording (truth B_eq 4.6, f_c 0.45) recorded ``late_s`` before its
    step: that many seconds of y = 0, v = 0 in front, the file still saying a step at t = 0."""
    from tuning.lab.data import builtin_dir

    rows = np.loadtxt(builtin_dir() / "p50.csv", delimiter=",", skiprows=1)
    n = int(round(late_s / 1e-3))
    rows = np.vstack([np.zeros((n, 3)), rows])
    rows[:, 0] = np.arange(len(rows)) * 1e-3
    columns = "t,y,v" if with_v else "t,y"
    np.savetxt(
        folder / "late.csv",
        rows[:, :3] if with_v else rows[:, :2],
        delimiter=",",
        header=columns,
        comments="",
        fmt="%.9g",
    )
    toml = (builtin_dir() / "p50.toml").read_text().replace("p50.csv", "late.csv")
    (folder / "late.toml").write_text(toml)
    return folder / "late.toml"


def test_a_step_recorded_late_is_found_from_the_voltage_and_used(tmp_path, capsys):
    """The issue's case: B_eq came out 30 +/- 0.934 kg/s (the upper edge of its range,
    unmarked, exit 0) from a P 50 run recorded 1 s before its step. The voltage jumps at 1 s:
    the step is taken there, said, and the fit finds the truth."""
    from jaxcart.files import read_experiment
    from tuning.commands.main import main

    path = _late_p50(tmp_path)
    rec = read_experiment(path)
    assert rec.warnings[0].startswith(
        f"{path}: the step starts at t = 1.000 s, not at t = 0 as [reference] says: the "
        "recorded command v stays at rest until then"
    )
    np.testing.assert_array_equal(rec.reference[:1000], 0.0)
    np.testing.assert_array_equal(rec.reference[1000:], 0.4)
    np.testing.assert_array_equal(np.asarray(rec.experiment.signal), rec.reference)
    assert "jaxcart: warning: " + rec.warnings[0] in capsys.readouterr().err  # said once
    assert (
        main(
            [
                "fit",
                str(path),
                "--params",
                "B_eq,f_c",
                "--quiet",
                "--json",
                str(tmp_path / "fit.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr()
    assert "EDGE" not in out.out
    import json

    params = json.loads((tmp_path / "fit.json").read_text())["params"]
    assert params["B_eq"]["value"] == pytest.approx(4.6, rel=0.005)  # the truth
    assert params["f_c"]["value"] == pytest.approx(0.45, rel=0.01)
    assert "at_edge" not in params["B_eq"]


def test_a_step_at_t_0_is_left_where_it_is():
    from jaxcart.files import read_experiment
    from tuning.lab.data import builtin_dir

    rec = read_experiment(builtin_dir() / "p50.toml")
    assert not any("step starts" in w for w in rec.warnings)
    np.testing.assert_array_equal(rec.reference, 0.4)


def test_a_fitted_value_on_the_edge_of_its_range_is_said_and_exits_1(tmp_path, capsys):
    """The issue's numbers, where nothing shows the step's real start (no column v): the fit
    runs to B_eq = 30 kg/s, the upper edge of its range. The value is marked as no estimate in
    the table, the warnings, the JSON and the plant file, and the command exits 1 (it is the
    headline)."""
    import json
    import tomllib

    from tuning.commands.main import main

    path = _late_p50(tmp_path, with_v=False)
    argv = ["fit", str(path), "--params", "B_eq,f_c", "--quiet"]
    argv += ["--json", str(tmp_path / "f.json"), "--out", str(tmp_path / "plant.toml")]
    assert main(argv) == 1
    out = capsys.readouterr()
    (row,) = [line for line in out.out.splitlines() if line.startswith("B_eq ")]
    assert row.split()[1] == "30" and row.endswith("AT THE UPPER EDGE of its range: no estimate")
    assert "warning: B_eq = 30 kg/s is at the upper edge of its allowed range [0.5, 30]" in out.out
    assert out.err.splitlines()[-1].startswith("fit: B_eq at the edge of the allowed range")
    doc = json.loads((tmp_path / "f.json").read_text())
    assert doc["params"]["B_eq"]["at_edge"] == {"side": "upper", "bound": 30.0}
    fit_table = tomllib.loads((tmp_path / "plant.toml").read_text())["fit"]
    assert any("upper edge" in w for w in fit_table["warnings"])


def test_an_edge_is_judged_relative_to_the_range_and_said_wherever_a_value_is_shown():
    from tuning.estimation.diagnose.report import _edge
    from tuning.estimation.engine.parameters import at_edge, bounds
    from tuning.lab.fits import pm

    lo, hi = bounds("B_eq")  # a logarithm: within 0.1 % of the bound
    assert at_edge("B_eq", hi) == ("upper", hi) and at_edge("B_eq", hi * 0.9995) == ("upper", hi)
    assert at_edge("B_eq", hi * 0.998) is None and at_edge("B_eq", lo) == ("lower", lo)
    lo, hi = bounds("y_rest")  # linear: within 0.1 % of the range's width
    assert at_edge("y_rest", lo + 0.0005 * (hi - lo)) == ("lower", lo)
    assert at_edge("y_rest", 0.0) is None and at_edge("v_sat@1", 30.0) == ("upper", 30.0)
    assert _edge("B_eq", 30.0) == ("upper", 30.0) and _edge("no_such", 1.0) is None
    est = fit.Estimate("B_eq", 30.0, 29.9, edge=("upper", 30.0))
    assert pm(est, "kg/s") == "30 ± 30 kg/s (at the upper edge of its allowed range: no estimate)"
    assert "upper edge of its allowed range [0.5, 30] kg/s" in est.edge_note


def test_an_encoder_count_is_found_whatever_the_origin_and_the_digits(realdata):
    """The real P 50 step's positions are whole counts; shifted by 0.2 m (an encoder not
    zeroed where the run starts), written to 10 significant digits or saved in single
    precision, they still are, and the count is the same (the floor, a run's start within its
    count and the counts in the loop follow from it: shifted, the real P 50 fitted to 9070
    times a floor of 0.001 mm where the file as recorded gives 1383 times 0.0066 mm);
    positions with noise are not counts."""
    from jaxcart.files import read_experiment
    from tuning.estimation.engine.noise import encoder_count

    y = np.asarray(read_experiment(f"{realdata}/p50.toml").position, dtype=float)
    q = encoder_count(y)
    assert q == pytest.approx(2.2735e-5, rel=1e-3)
    assert encoder_count(y - 0.2) == pytest.approx(q, rel=1e-9)
    assert encoder_count(y + 0.3 * q) == pytest.approx(q, rel=1e-9)
    ten_digits = np.array([float(f"{v:.10g}") for v in y - 0.2])
    assert encoder_count(ten_digits) == pytest.approx(q, rel=1e-6)
    # Saved in single precision (a scope's float32 .mat): 1.5e-8 m off at 0.4 m, still counts.
    single = (y - 0.2).astype(np.float32).astype(float)
    assert encoder_count(single) == pytest.approx(q, rel=1e-4)
    noisy = y + np.random.default_rng(0).normal(0.0, 1e-6, y.size)
    assert encoder_count(noisy) == 0.0


def test_encoder_counts_written_to_9_digits_or_6_decimals_and_noise_written_to_1_um():
    """Another author's encoder (1024 or 4096 counts of a 14.8 mm pinion) written with numpy's
    "%.9g" over 0.1-0.31 m (a 9-digit value starting with 1 is off by up to 5e-9 |y|, beyond
    the old 1e-9 |y|, and the smallest step between such values by 3e-5 of a count) or with
    "%.6f" (1 um: the smallest step 3 % off) is still whole counts; white noise of 20 um written
    with "%.6f" is not an encoder of 1 um counts (its floor would be 0.001 mm, not 0.02 mm)."""
    from tuning.estimation.engine.noise import encoder_count

    t = np.arange(2500) * 1e-3
    x = 0.31 * (1 - np.exp(-3 * t)) * (1 + 0.02 * np.sin(7 * t))
    for counts in (1024, 4096):
        q = 2 * np.pi * 0.0148 / counts
        y = np.floor(x / q) * q
        for fmt in ("%.9g", "%.6f"):
            written = np.array([float(fmt % v) for v in y])
            assert encoder_count(written) == pytest.approx(q, rel=1e-5), (counts, fmt)
    noise = x + np.random.default_rng(1).normal(0.0, 20e-6, x.size)
    assert encoder_count(np.round(noise, 6)) == 0.0


def test_an_encoder_named_in_the_plant_is_read_in_the_loop_and_the_cart_compared(tmp_path):
    """A P step of the independent generator, whose controller read whole counts, with the
    encoder named in its [plant] (quantization = q): the fit's controller reads the counts and
    the cart's own position is compared with the recording, as the diagnosis does; the
    optimizer converges and each value lies within 3 of its standard errors of the truth
    (measured -1.5, 1.3, 0.8, the same from the handout's start; -6.6, 4.1, -7.5 with the
    encoder not named). (The counts' staircase compared gave the optimizer its cap and v_sat
    5.69934 +- 0.000003 V for 5.7: 220 standard errors; the exact polish's differences of 1e-6
    caught count flips, and from B_eq and f_c read off the data f_c lay 11 standard errors
    off, its error 3.7e-5 N.)"""
    import jaxcart as jc
    from jaxcart.files import read_experiment
    from tuning.estimation.fit import fit
    from tuning.verification import REALISTIC, TrueCart
    from tuning.verification import experiments as ex
    from tuning.verification import make_recording as make_independent

    truth = {"B_eq": 3.0, "f_c": 0.2, "v_sat": 5.7}
    # (What else real recordings carry, jitter and the encoder's phase, stays; the amplifier's
    # 0.1 ms lag, which no structure here has, moves v_sat by 0.1 %, 40 standard errors.)
    art = REALISTIC.replace(
        gain_spread=0.0, limit_spread=0.0, drift_gain=0.0, drift_offset=0.0, lag=0.0
    )
    step = ex.step(jc.PID(kp=50.0, v_limit=6.0), 0.4, horizon=1.5)
    path = make_independent(TrueCart.from_values(truth), step, tmp_path / "p50.toml", art).path
    path.write_text(path.read_text() + "\n[plant]\nquantization = 2.275e-5\n")
    result = fit([read_experiment(path)], ("B_eq", "f_c", "v_sat"), progress=False)
    assert not result.warnings, result.warnings
    for name, value in truth.items():
        e = result.params[name]
        assert abs(e.value - value) < 3 * e.stderr, (name, e.value, e.stderr)
