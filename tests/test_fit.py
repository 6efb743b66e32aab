"""Fitting plant parameters (tuning/estimation/fit.py): accuracy and standard errors on recordings
made by the
exact simulator through the encoder (jaxcart/synthetic.py), identifiability, the fitted-plant file,
the command line, and the real recordings."""

import json
import math
import os

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.errors import UserError
from jaxcart.synthetic import make_recording, make_tap_recording, write_recording
from tuning.estimation import fit
from tuning.estimation.engine.segments import coasting_segment
from tuning.estimation.fitting.model import _Problem

Q = jc.ENCODER_RESOLUTION
P50 = jc.PID(kp=50.0, v_limit=6.0)
TAP_TRUTH = {"B_eq": 1.5, "f_c": 0.44}  # close to the real cart's tap fit
CL_TRUTH = {"B_eq": 2.5, "f_c": 0.3}


@pytest.fixture(scope="module")
def tap_rec():
    truth = jc.tap_plant(B_eq=TAP_TRUTH["B_eq"], effects=(jc.Coulomb(f_c=TAP_TRUTH["f_c"]),))
    return make_tap_recording(truth, speed=1.0, rest=0.3, push_time=0.1, horizon=1.7, seed=11)


@pytest.fixture(scope="module")
def tap_fit(tap_rec):
    return fit.fit([tap_rec], ("B_eq", "f_c"), progress=False)


@pytest.fixture(scope="module")
def cl_rec():
    truth = jc.handout_plant(**CL_TRUTH)
    return make_recording(truth, P50, jc.step(0.4, horizon=1.5), seed=5)


@pytest.fixture(scope="module")
def cl_fit(cl_rec):
    return fit.fit([cl_rec], ("B_eq", "f_c"), progress=False)


def _check_accuracy(result, truth):
    b, f = result.params["B_eq"], result.params["f_c"]
    assert b.value == pytest.approx(truth["B_eq"], rel=0.01)
    assert f.value == pytest.approx(truth["f_c"], rel=0.03)
    for e in (b, f):
        assert abs(e.value - truth[e.name]) < 3 * e.stderr
        assert e.stderr >= e.stderr_naive * 0.5  # robust errors are never much smaller


def test_tap_fit_finds_the_coasting_part_and_the_truth(tap_rec, tap_fit):
    seg = tap_fit.segments[0]
    # The push ends at 0.4 s; coasting starts 20 ms after the peak speed.
    assert 0.4 <= seg.time[0] <= 0.45
    true_v = np.gradient(tap_rec.true_position, 1e-3)
    stop = tap_rec.time[np.flatnonzero(np.abs(true_v) > 0)[-1]]  # the exact cart's stop
    assert stop <= seg.time[-1] <= stop + 0.06
    _check_accuracy(tap_fit, TAP_TRUTH)
    # The fitted exact model explains the data to the encoder's own error, q / sqrt(12).
    assert tap_fit.rms_after_exact < 1.2 * Q / math.sqrt(12)
    # From B_eq and f_c read off the coasting (0.2 mm; the handout's start was 100 times off).
    assert tap_fit.rms_before_exact > 10 * tap_fit.rms_after_exact
    assert abs(tap_fit.rms_after - tap_fit.rms_after_exact) < 2e-6  # smooth ~ exact


def test_closed_loop_fit_finds_the_truth(cl_fit):
    _check_accuracy(cl_fit, CL_TRUTH)
    assert cl_fit.rms_after_exact < 1.2 * Q / math.sqrt(12)
    # y0 lies in the first count of the encoder (a bounded nuisance).
    y0 = cl_fit.segments[0].nuisance["y0"].value
    assert -1e-12 <= y0 <= Q + 1e-12


def test_stuck_cart_step_fits_from_the_default_start():
    """The built-in P 50 step (exact simulator, encoder; the cart ends stuck 0.25 V short):
    from the default start (B_eq = 5.4 kg/s, f_c = 0.3 N) the wide-width continuation lets
    the cart creep and B_eq take up the friction (it ended at 1.5 mm RMS, f_c not
    identifiable); the direct start at the narrowest width finds the truth, to the encoder's
    own error."""
    from pathlib import Path

    from jaxcart.files import read_experiment
    from tuning.lab.data import TRUE

    rec = read_experiment(Path(jc.__file__).parent / "data" / "p50.toml")
    result = fit.fit([rec], ("B_eq", "f_c"), progress=False)
    assert result.params["B_eq"].value == pytest.approx(TRUE["B_eq"], rel=0.005)
    assert result.params["f_c"].value == pytest.approx(TRUE["f_c"], rel=0.005)
    assert result.rms_after_exact < 1.2 * TRUE["quantization"] / math.sqrt(12)
    # The continuation's run, stopped at its cap, was discarded: it judges nothing.
    assert any(s.get("superseded") for s in result.stages)
    assert result.converged and not result.warnings, result.warnings


def test_joint_fit_of_tap_and_closed_loop(tap_rec):
    truth = jc.handout_plant(**TAP_TRUTH)
    cl = make_recording(truth, P50, jc.step(0.4, horizon=1.5), seed=2)
    result = fit.fit(
        [tap_rec, cl], ("B_eq", "f_c"), progress=False, settings=fit.FitSettings(adam_steps=0)
    )
    _check_accuracy(result, TAP_TRUTH)
    assert [s.kind for s in result.segments] == ["tap", "closed_loop"]
    # Each recording alone predicts the other (cross-prediction) to near the encoder error.
    pred = fit.cross_predict(result.values, [cl])
    assert pred.rms_after_exact < 2 * Q


def test_fit_v_limit_and_gamma_scale():
    # A saturated step also determines the amplifier's limit (v_limit = v_sat) and gain.
    truth = {"B_eq": 2.5, "f_c": 0.3, "v_sat": 5.0, "gamma_scale": 0.9}
    rec = make_recording(jc.handout_plant(**truth), P50, jc.step(0.4, horizon=1.5), seed=5)
    params = ("B_eq", "f_c", "v_limit", "gamma_scale")
    result = fit.fit([rec], params, progress=False, settings=fit.FitSettings(adam_steps=0))
    for name in params:
        e = result.params[name]
        assert e.value == pytest.approx(truth[fit.canonical(name)], rel=0.01), name
        assert abs(e.value - truth[fit.canonical(name)]) < 3 * e.stderr, name


def _coverage(kind, seeds, noise=0.0):
    """z = (estimate - truth) / stderr over seeds, truths drawn at random per seed."""
    z = {"B_eq": [], "f_c": []}
    settings = fit.FitSettings(adam_steps=0, widths=(1e-3, 1e-4))
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        tv = {"B_eq": rng.uniform(2.0, 3.0), "f_c": rng.uniform(0.4, 0.6)}
        if kind == "tap":
            truth = jc.tap_plant(B_eq=tv["B_eq"], effects=(jc.Coulomb(f_c=tv["f_c"]),))
            rec = make_recording(truth, None, jc.tap(1.0, horizon=0.5), seed=seed, noise=noise)
        else:
            truth = jc.handout_plant(**tv)
            rec = make_recording(truth, P50, jc.step(0.4, horizon=1.2), seed=seed, noise=noise)
        result = fit.fit([rec], ("B_eq", "f_c"), settings=settings, progress=False)
        for k, e in result.params.items():
            z[k].append((e.value - tv[k]) / e.stderr)
    return {k: np.abs(np.array(v)) for k, v in z.items()}


def test_stderr_coverage_small():
    # 16 taps; deterministic seeds, so the counts below are fixed numbers, not chance.
    z = _coverage("tap", range(16))
    for k, a in z.items():
        assert 0.5 <= np.mean(a < 1) <= 0.95, (k, a)
        assert np.mean(a < 2) >= 0.85, (k, a)


@pytest.mark.slow
@pytest.mark.parametrize("kind, noise", [("tap", 0.0), ("closed_loop", 0.0), ("tap", 2e-5)])
def test_stderr_coverage_many_seeds(kind, noise):
    z = _coverage(kind, range(40), noise)
    for k, a in z.items():
        assert 0.55 <= np.mean(a < 1) <= 0.9, (k, np.mean(a < 1))
        assert 0.88 <= np.mean(a < 2), (k, np.mean(a < 2))


def test_not_identifiable(tap_rec):
    # gamma_scale does nothing to a tap (motor unplugged); M only scales B_eq and f_c; f_c from
    # a short, fast coast (never slow) with a noisy sensor cannot be told from B_eq.
    settings = fit.FitSettings(adam_steps=0)
    result = fit.fit(
        [tap_rec], ("B_eq", "f_c", "gamma_scale", "M"), settings=settings, progress=False
    )
    assert result.params["B_eq"].identifiable and result.params["f_c"].identifiable
    g, m = result.params["gamma_scale"], result.params["M"]
    assert g.value is None and g.stderr is None and "do not depend" in g.note
    assert m.value is None and "combination" in m.note
    assert result.to_json()["params"]["M"]["identifiable"] is False
    truth = jc.tap_plant(B_eq=2.5, effects=(jc.Coulomb(f_c=0.5),))
    fast = make_recording(truth, None, jc.tap(1.0, horizon=0.12), seed=0, noise=5e-5)
    result = fit.fit([fast], ("B_eq", "f_c"), settings=settings, progress=False)
    assert not result.params["f_c"].identifiable and result.params["f_c"].value is None
    assert result.params["B_eq"].identifiable


def test_a_limit_the_run_never_reaches_is_held_where_it_does_not_act():
    """A PD loop following a ramp, its command never above 1.35 V, v_sat asked for beside
    B_eq and f_c: the data do not depend on a limit above the command, so v_sat is not
    identifiable, and it is held where the fit left it (30 V, the top of its range), not at
    its start, 0.7 times the largest command, where it clips the drive: held there, the fit
    lost B_eq and f_c too (not identifiable, 0.067 mm after, ten times the floor); on the
    independent generator's sine under PD it came out worse than the model before it. Held
    where it was, it leaves the others' fit as it is: no refit without it."""
    truth = jc.handout_plant(B_eq=2.0, f_c=0.35)
    rec = make_recording(truth, jc.PID(kp=40.0, kd=3.0), jc.ramp(0.2, horizon=1.5), seed=3)
    peak = float(np.max(np.abs(rec.command)))
    assert peak < 1.5
    result = fit.fit([rec], ("B_eq", "f_c", "v_sat"), progress=False)
    v = result.params["v_sat"]
    assert not v.identifiable and v.held_at > peak and "a limit the runs never reached" in v.note
    assert result.params["B_eq"].value == pytest.approx(2.0, rel=0.01)
    assert result.params["f_c"].value == pytest.approx(0.35, rel=0.03)
    assert result.rms_after < 2 * result.noise_floor
    assert not any("without v_sat" in s["stage"] for s in result.stages)


def test_parameter_names():
    assert fit.parse_params("B_eq, f_c,v_limit") == ("B_eq", "f_c", "v_limit")
    assert fit.canonical("v_limit") == "v_sat"
    with pytest.raises(UserError, match="unknown parameter 'B'"):
        fit.parse_params("B,f_c")
    with pytest.raises(UserError, match="named twice"):
        fit.parse_params("v_sat,v_limit")
    plant = fit.with_values(jc.handout_plant(), {"f_c": 0.4, "v_limit": 5.0})
    assert plant.get("f_c") == 0.4 and plant.get("v_sat") == 5.0


def test_coasting_segment_needs_a_tap():
    with pytest.raises(ValueError, match="no tap"):
        coasting_segment(np.zeros(500), 1e-3)


def test_a_tap_timed_in_milliseconds_is_named_so():
    """A tap whose time column is in ms (the sample time read as 1 s) moves 0.5 m at under 1 mm
    per "second": the refusal names the time's unit, not a cart that does not move."""
    t = np.arange(3000) * 1e-3
    y = 0.5 * (1 - np.exp(-t / 0.6))  # 0.83 m/s at first: the real tap's speed
    with pytest.raises(ValueError, match=r"moves 0\.49\d m .*time recorded in ms"):
        coasting_segment(y, 1.0)


def test_a_value_held_says_where_to_give_another(tap_rec):
    """The advice for a value the data do not determine names what ``jaxcart fit`` takes: a
    plant file (--plant) or the recording's [plant] table (there is no --initial)."""
    seg = fit.fit_segment(tap_rec, ("B_eq", "f_c"), {}, fit.FitSettings())
    text = _Problem([seg], ("B_eq", "f_c"), fit.FitSettings()).start_source("f_c")
    assert "--plant FILE" in text and "[plant]" in text and "--initial" not in text


def test_fitted_plant_file_round_trip(tmp_path, cl_fit):
    from jaxcart.plantspec import read_plant_file

    path = fit.write_fitted_plant(tmp_path / "fitted.toml", cl_fit, sources=["a.toml"])
    plant, fit_table = read_plant_file(path)
    assert plant == fit.load_fitted_plant(path) == cl_fit.plant()  # the effects come back too
    assert plant.motor_connected and plant.structure == ("coulomb",)  # P50 limits in software
    assert plant.get("B_eq") == pytest.approx(cl_fit.params["B_eq"].value, rel=1e-12)
    assert plant.get("f_c") == pytest.approx(cl_fit.params["f_c"].value, rel=1e-12)
    assert fit_table["stderr"]["B_eq"] == pytest.approx(cl_fit.params["B_eq"].stderr)
    assert fit_table["recordings"] == ["a.toml"] and fit_table["held"] == []
    with pytest.raises(UserError, match="exists"):
        fit.write_fitted_plant(path, cl_fit)
    fit.write_fitted_plant(path, cl_fit, force=True)
    bad = tmp_path / "bad.toml"
    bad.write_text('format = "jaxcart-plant"\n[plant]\nB_eq = -1.0\n')
    with pytest.raises(UserError, match="B_eq"):
        fit.load_fitted_plant(bad)
    with pytest.raises(UserError, match="not found"):
        fit.load_fitted_plant(tmp_path / "missing.toml")


def test_command_line(tmp_path, tap_rec, capsys):
    from tuning.commands.main import main

    toml = write_recording(tap_rec, tmp_path / "tap.toml")
    args = [
        "fit",
        str(toml),
        "--params",
        "B_eq,f_c",
        "--quiet",
        "--classic",
        "--json",
        str(tmp_path / "fit.json"),
        "--out",
        str(tmp_path / "fitted.toml"),
        "--plot",
        str(tmp_path / "fit.png"),
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "B_eq" in out and "log-linear" in out and "exact simulator" in out
    report = json.loads((tmp_path / "fit.json").read_text())
    assert report["params"]["B_eq"]["value"] == pytest.approx(TAP_TRUTH["B_eq"], rel=0.01)
    assert report["rms_after"] < report["rms_before"]
    assert report["classic"][0]["name"] == "B_eq"
    assert (tmp_path / "fit.png").stat().st_size > 10_000
    assert fit.load_fitted_plant(tmp_path / "fitted.toml").get("f_c") == pytest.approx(
        report["params"]["f_c"]["value"]
    )
    # Existing outputs are kept unless --force; the error is one line, before any fitting.
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["fit", str(toml), "--params", "B_eq,wheels"]) == 2
    assert "unknown parameter" in capsys.readouterr().err


def test_real_tap(realdata):
    from jaxcart.files import read_experiment

    rec = read_experiment(os.path.join(realdata, "tap.toml"))
    result = fit.fit([rec], ("B_eq", "f_c"), progress=False)
    seg = result.segments[0]
    assert 3.1 <= seg.time[0] <= 3.5  # the push ends at about 3.28 s
    assert 4.2 <= seg.time[-1] <= 4.5  # at rest again by about 4.4 s
    b, f = result.params["B_eq"], result.params["f_c"]
    print(
        f"real tap: B_eq = {b.value:.4g} +/- {b.stderr:.2g} kg/s, f_c = {f.value:.4g} +/- "
        f"{f.stderr:.2g} N, RMS {result.rms_before_exact * 1e3:.4g} -> "
        f"{result.rms_after_exact * 1e3:.4g} mm"
    )
    assert 0.5 < b.value < 5.4 and 0.05 < f.value < 1.5
    # Model error (not the encoder) dominates: the robust errors exceed the naive ones.
    assert b.stderr > 2 * b.stderr_naive
    assert result.rms_after_exact < 1e-3 < result.rms_before_exact


@pytest.mark.slow
def test_real_cross_prediction(realdata):
    from jaxcart.files import read_experiment
    from tuning.estimation.cross_fit import cross_table

    recs = [read_experiment(os.path.join(realdata, f)) for f in ("tap.toml", "p50.toml")]
    rows = cross_table(recs, ("B_eq", "f_c"))
    for row in rows:
        print(
            f"{row['fitted_on']} -> {row['predicting']}: {row['rms'] * 1e3:.4g} mm {row['values']}"
        )
        assert math.isfinite(row["rms"])


def test_the_fits_adam_is_optax_adam():
    """The fit's adam stage takes optax.adam's steps with optax's cosine-decayed rate, on the
    active entries alone, and returns the best point it met."""
    import jax.numpy as jnp
    import optax

    from tuning.estimation.engine.least_squares import adam

    a = np.array([[1.0, 0.5], [0.0, 3.0], [2.0, -1.0]])
    b = np.array([0.3, -1.0, 2.0])

    class Linear:
        def evaluate(self, theta, width):
            return a @ theta[:2] - b, np.hstack([a, np.zeros((3, 1))])

        def objective(self, r):
            return float(r @ r), None

    theta0 = np.array([1.0, -2.0, 7.0])
    active = np.array([True, True, False])
    steps, lr = 15, 0.1
    best, best_r = adam(Linear(), theta0, active, 0.0, steps, lr)
    opt = optax.adam(optax.cosine_decay_schedule(lr, steps))
    x = jnp.asarray(theta0[:2])
    state = opt.init(x)
    ref_best, ref_cost = None, math.inf
    for _ in range(steps):
        r = a @ np.asarray(x) - b
        cost = float(r @ r)
        if cost < ref_cost:
            ref_best, ref_cost = np.asarray(x).copy(), cost
        updates, state = opt.update(jnp.asarray(a.T @ r / cost), state, x)
        x = optax.apply_updates(x, updates)
    np.testing.assert_allclose(best[:2], ref_best, rtol=1e-12, atol=1e-14)
    assert best[2] == 7.0 and float(best_r @ best_r) == pytest.approx(ref_cost, rel=1e-12)


def test_a_value_held_at_a_given_start_says_it_was_given(tap_rec):
    """Held at a start value the caller gave (jaxcart lab: Part (i)'s B_eq), the note says so,
    not that it is the handout's."""
    seg = fit.fit_segment(tap_rec, ("B_eq", "f_c"), {"B_eq": 1.5}, fit.FitSettings())
    problem = _Problem([seg], ("B_eq", "f_c"), fit.FitSettings(), given={"B_eq": 1.5})
    assert "what the fit was given" in problem.start_source("B_eq")
    assert "typical value" in problem.start_source("f_c")


def test_a_fit_at_a_neighbouring_answer_is_the_exact_polish_alone(cl_rec, cl_fit):
    """FitSettings.exact_only (the lab's driven runs alone from the joint fit's values): from
    values 3 standard errors off, the exact polish alone reaches the full fit's values (its
    continuation, adam and Levenberg-Marquardt) within a tenth of a standard error, and no
    smooth stage runs."""
    start = {n: e.value + 3 * e.stderr for n, e in cl_fit.params.items()}
    near = fit.fit([cl_rec], ("B_eq", "f_c"), initial=start, settings=fit.FitSettings.exact_only(),
                   progress=False)  # fmt: skip
    assert [s["stage"] for s in near.stages] == ["Gauss-Newton on the exact simulator"]
    assert near.stages[0]["converged"]
    for name, e in cl_fit.params.items():
        assert abs(near.params[name].value - e.value) < 0.1 * e.stderr, name
        assert near.params[name].stderr == pytest.approx(e.stderr, rel=0.05), name


def test_a_plant_file_with_the_handouts_b_eq_gives_it(tmp_path):
    """--plant gives B_eq even where the file keeps the handout's 5.4 kg/s (plant_values leaves
    a value equal to the handout's out): the fit starts there, not where the recordings put it."""
    import jaxcart as jc
    from jaxcart.plantspec import write_plant_file
    from tuning.commands.fit import _initial

    path = tmp_path / "hand.toml"
    write_plant_file(path, jc.handout_plant(f_c=0.3))
    assert _initial(str(path)) == pytest.approx({"B_eq": 5.4, "f_c": 0.3})
