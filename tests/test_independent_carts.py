"""The lab end to end on the independent generator's carts (python -m
tuning.benchmark.independent_carts): its machinery, not the proof (a cart takes minutes; the
benchmark prints the proof): the handout's experiments, one cart judged by its gains file's band
on the true cart, the summary the issue judges by, the options."""

import json

import pytest

from hw.control_law import PID
from hw.gains import write_gains
from tuning.benchmark import independent_carts as ic
from tuning.lab import data
from tuning.verification import REALISTIC, TrueCart, run_controller

#: Gains that settle the base cart (docs/hardware.md's): the handed back and the pre-lab's here.
GAINS = PID(kp=120.9, ki=1.67, kd=4.1, tau=0.01, v_limit=6.0)


def test_the_handouts_recordings_are_its_experiments_with_the_prelabs_pid():
    experiments = ic.experiments(GAINS)
    assert list(experiments) == [s.stem for s in data.SPECS]
    for spec in data.SPECS:
        assert experiments[spec.stem].kind == spec.kind
        controller = experiments[spec.stem].pid
        if spec.slot == "pid":
            assert controller == GAINS
        elif spec.kind == "closed_loop":
            assert controller == PID(**spec.controller)


def _report(folder, prediction):
    folder.mkdir()
    write_gains(folder / "gains.json", GAINS, prediction=prediction, binding="the 6 V limit")
    return folder


def test_a_cart_is_judged_by_its_gains_files_band_on_the_true_cart(tmp_path):
    """The true run is the independent generator's (the recordings' artefacts, the cart's own
    drive); the row's settling error and whether the truth is inside the band are the gains
    file's prediction against that run (tolerance: the metrics' 1 ms sample)."""
    cart = TrueCart.from_values(ic.BASE)
    artefacts = REALISTIC.replace(**ic.TRUE_RUN)
    truth = run_controller(cart, GAINS, artefacts=artefacts, seed=3).metrics
    t = truth.settling_time
    band = {"nominal": t + 0.010, "band": [t - 0.005, t + 0.020]}
    prediction = {"level": 0.9, "p_meet": 0.9, "metrics": {"settling_time": band}}
    row = ic.judge("friction", cart, _report(tmp_path / "in", prediction), {}, GAINS, 3)
    assert row["true_settling"] == pytest.approx(t, abs=1e-3) and row["inside"]
    assert row["error"] == pytest.approx(0.010, abs=1e-3) and row["meets"] == truth.meets()
    assert row["prelab_settling"] == pytest.approx(t, abs=1e-3) and row["binding"]
    band = {"nominal": t - 0.050, "band": [t - 0.060, t - 0.040]}
    prediction["metrics"]["settling_time"] = band
    row = ic.judge("friction", cart, _report(tmp_path / "out", prediction), {}, GAINS, 3)
    assert not row["inside"] and row["error"] == pytest.approx(-0.050, abs=1e-3)


def test_the_summary_is_what_the_issue_judges_by():
    def row(error, inside=True, meets=True):
        return {
            "cart": "c", "gains": {"kp": 1.0, "ki": 1.0, "kd": 1.0}, "p_meet": 1.0,
            "predicted_settling": 0.7 + error, "band": [0.6, 0.8], "model_error": 0.01,
            "true_settling": 0.7, "inside": inside, "error": error, "true_overshoot": 1.0,
            "meets": meets, "prelab_settling": 0.9, "prelab_meets": meets,
        }  # fmt: skip

    rows = [row(0.01), row(-0.04, inside=False), row(0.02, meets=False)]
    s = ic.summary(rows)
    assert s["median_error"] == pytest.approx(0.02) and s["carts"] == 3
    assert not s["all_inside"] and not s["all_meet"] and s["prelab_meets"] == 2
    text = ic.table({"rows": rows, "summary": s, "diagnosis": False})
    assert "inside the predicted band: 2 of 3" in text and "median |error|" in text
    assert "20.0 ms" in text and "without diagnosis" in text


def test_unknown_carts_are_refused(capsys):
    with pytest.raises(SystemExit) as e:
        ic.main(["--only", "friction,a rocket"])
    assert e.value.code == 2 and "--only" in capsys.readouterr().err
    assert json.dumps(list(ic.CARTS))  # the names as the option takes them
