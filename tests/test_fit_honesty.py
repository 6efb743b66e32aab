"""What a fit says about itself (tuning/estimation/fit.py): a model that does not explain the data
is
flagged and its standard errors widened to what the residual supports; an optimizer stopped at
its cap says so; outputs are checked before any fitting; the batched Levenberg-Marquardt
evaluates K trial points as K single runs would, without recompiling. References: the encoder's
q / sqrt(12) and the white noise against the recording's own true positions, and the AR(1)
integrated autocorrelation time (1 + rho) / (1 - rho)."""

import math

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.synthetic import make_recording, write_recording
from tuning.estimation import fit as F
from tuning.estimation.engine.noise import MISFIT_RATIO, effective_samples

Q = jc.ENCODER_RESOLUTION
TRUTH = {"B_eq": 3.0, "f_c": 0.5}
#: One width and few iterations: these tests check what a fit reports, not its accuracy
#: (tests/test_fit.py does that with the default settings).
QUICK = F.FitSettings(widths=(1e-3, 1e-4), adam_steps=0)


@pytest.fixture(scope="module")
def tap():
    truth = jc.tap_plant(B_eq=TRUTH["B_eq"], effects=(jc.Coulomb(f_c=TRUTH["f_c"]),))
    return make_recording(truth, None, jc.tap(1.0, horizon=0.6), seed=0)


@pytest.fixture(scope="module")
def good(tap):
    return F.fit([tap], ("B_eq", "f_c"), settings=QUICK, progress=False)


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
    bad = F.fit([tap], ("B_eq",), settings=QUICK, progress=False)
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
    table = F.fit_table(bad)
    assert table["model_explains_data"] is False and table["warnings"] == bad.warnings


def test_an_optimizer_at_its_cap_says_so(tap, good):
    layout_traces = dict(F.TRACES)
    capped = F.fit(
        [tap],
        ("B_eq", "f_c"),
        settings=F.FitSettings(widths=(1e-2,), adam_steps=0, lm_iterations=1),
        exact=False,
        progress=False,
    )
    assert not capped.converged and capped.to_json()["converged"] is False
    stage = capped.stages[0]
    assert stage["iterations"] == stage["cap"] == 1 and not stage["converged"]
    assert any("stopped at its iteration cap (1)" in w for w in capped.warnings)
    assert F.fit_table(capped)["converged"] is False
    # Same recording and parameters, another width and cap: the compiled program is reused.
    assert F.TRACES == layout_traces


def test_batched_trials_equal_single_runs(tap):
    seg = F.prepare(tap, ("B_eq", "f_c"), {}, QUICK)
    problem = F._Problem([seg], ("B_eq", "f_c"), QUICK)
    points = problem.theta0 + np.array([[0.0, 0.0, 0.0, 0.0], [0.1, -0.2, 0.5, 0.3]])
    r_k, j_k = problem.evaluate_batch(points, 1e-3)
    for k, theta in enumerate(points):
        r, jac = problem.evaluate(theta, 1e-3)
        np.testing.assert_allclose(r_k[k], r, rtol=0, atol=1e-12)
        np.testing.assert_allclose(j_k[k], jac, rtol=1e-10, atol=1e-12)
    assert not np.allclose(r_k[0], r_k[1])


def test_noise_floor_against_the_true_positions():
    truth = jc.handout_plant(B_eq=2.5, f_c=0.3)
    for noise in (0.0, 2e-5):
        rec = make_recording(truth, jc.PID(kp=20.0), jc.ramp(0.2, horizon=2.0), seed=4, noise=noise)
        seg = F.prepare(rec, ("B_eq",), {}, F.FitSettings())
        # About its mean: a constant offset (the count's phase in noisy data) is y0's part.
        err = seg.measured - rec.true_position
        assert F.noise_floor([seg]) == pytest.approx(np.std(err), rel=0.1), noise


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
