"""Gains files (hw/gains.py): every PID setting survives a round trip, bad files give errors that
name the file and the field, and hw/ never imports jax."""

import json
import math
import subprocess
import sys
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest

from hw.control_law import PID
from hw.gains import CONTROLLER_FIELDS, GainsFileError, read_gains, read_gains_file, write_gains

ROOT = Path(__file__).resolve().parents[1]

CONTROLLERS = [
    PID(kp=258.7566102523228, ki=1.7040361957982133, kd=6.133625299079171, v_limit=6.0),
    PID(kp=40.0, kd=5.0, ki=5.0, tau=0.0, v_limit=math.inf, derivative_on="measurement"),
    PID(kp=10.0, ki=15.0, kb=2.5, sample_time=0.002, v_limit=6.0, anti_windup="back_calculation"),
    PID(kp=50.0, anti_windup="clamping", v_limit=4.5),
]


@pytest.mark.parametrize("pid", CONTROLLERS)
def test_round_trip_keeps_every_setting(tmp_path, pid):
    path = write_gains(tmp_path / "gains.json", pid)
    back = read_gains(path)
    assert back == pid  # every field, exactly (JSON floats round-trip in repr form)
    assert set(back.to_dict()) == set(CONTROLLER_FIELDS)


def test_inf_limit_is_null_in_the_file_and_inf_string_is_accepted(tmp_path):
    path = write_gains(tmp_path / "g.json", PID(kp=1.0, v_limit=math.inf))
    doc = json.loads(path.read_text())
    assert doc["controller"]["v_limit"] is None
    doc["controller"]["v_limit"] = "inf"
    path.write_text(json.dumps(doc))
    assert read_gains(path).v_limit == math.inf


def test_metadata_numpy_namedtuple_and_nonfinite(tmp_path):
    Info = namedtuple("Info", "settling_time overshoot diverged")
    path = write_gains(
        tmp_path / "g.json",
        PID(kp=1.0),
        metrics=Info(np.float64(0.708), math.inf, np.bool_(False)),
        plant={"B_eq": 5.4, "M": np.float32(0.94)},
        history=np.array([1.0, 2.0]),
        source=tmp_path / "fit.json",
    )
    pid, meta = read_gains_file(path)
    assert pid.kp == 1.0
    assert meta["metrics"] == {"settling_time": 0.708, "overshoot": "inf", "diverged": False}
    assert meta["plant"]["B_eq"] == 5.4 and meta["history"] == [1.0, 2.0]
    assert meta["source"].endswith("fit.json")
    assert "date" in meta and meta["date"][:2] == "20"
    assert "format" not in meta and "controller" not in meta


def test_never_overwrites_without_force(tmp_path):
    path = write_gains(tmp_path / "g.json", PID(kp=1.0))
    with pytest.raises(GainsFileError, match="exists.*force") as info:
        write_gains(path, PID(kp=2.0))
    assert str(path) in str(info.value)
    assert read_gains(path).kp == 1.0
    write_gains(path, PID(kp=2.0), force=True)
    assert read_gains(path).kp == 2.0
    assert [p.name for p in tmp_path.iterdir()] == ["g.json"]  # no temporary left behind


def _write(tmp_path, controller, **top):
    doc = {"format": "jaxcart-gains", "version": 1, "controller": controller, **top}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    return path


def _good():
    return PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0).to_dict()


@pytest.mark.parametrize(
    "change, field, words",
    [
        ({"kp": None}, "controller.kp", "give a number"),
        ({"kd": "5"}, "controller.kd", "give a number"),
        ({"ki": True}, "controller.ki", "give a number"),
        ({"kp": -1.0}, "controller.kp", ">= 0"),
        ({"sample_time": 0.0}, "controller.sample_time", "positive"),
        ({"derivative_on": "output"}, "controller.derivative_on", "error, measurement"),
        ({"anti_windup": "clip"}, "controller.anti_windup", "clamping"),
        ({"Kp": 1.0}, "controller.Kp", "unknown field"),
    ],
)
def test_bad_field_names_file_and_field(tmp_path, change, field, words):
    controller = _good()
    controller.update(change)
    path = _write(tmp_path, controller)
    with pytest.raises(GainsFileError) as info:
        read_gains(path)
    err = info.value
    assert isinstance(err, ValueError)
    assert err.field == field and err.path == str(path)
    assert str(path) in str(err) and field in str(err) and words in str(err)


def test_overflowing_number_is_not_finite(tmp_path):
    text = json.dumps({"controller": _good()}).replace('"tau": 0.01', '"tau": 1e400')
    path = tmp_path / "g.json"
    path.write_text(text)
    with pytest.raises(GainsFileError, match="controller.tau: inf s: give a finite number"):
        read_gains(path)


def test_missing_fields_are_listed(tmp_path):
    controller = _good()
    del controller["tau"], controller["anti_windup"]
    with pytest.raises(GainsFileError, match="missing field.*tau, anti_windup") as info:
        read_gains(_write(tmp_path, controller))
    assert info.value.field == "controller.tau"


@pytest.mark.parametrize(
    "text, words",
    [
        ("{not json", "not a JSON gains file"),
        ('{"controller": {"kp": NaN}}', "NaN is not a JSON number"),
        ("[1, 2]", "expected a JSON object"),
        ('{"kp": 40}', 'missing the "controller"'),
        ('{"format": "other", "controller": {}}', "format"),
        ('{"version": 2, "controller": {}}', "version"),
    ],
)
def test_bad_documents(tmp_path, text, words):
    path = tmp_path / "g.json"
    path.write_text(text)
    with pytest.raises(GainsFileError, match=words):
        read_gains(path)


def test_missing_file(tmp_path):
    with pytest.raises(GainsFileError, match="no such file"):
        read_gains(tmp_path / "nope.json")


def test_write_rejects_what_read_would_reject(tmp_path):
    with pytest.raises(GainsFileError, match="controller.kp"):
        # PID(kp=nan) itself is refused (ValueError); an array leaf reaches write_gains.
        write_gains(tmp_path / "g.json", PID(kp=np.array(math.nan)))
    with pytest.raises(GainsFileError, match="reserved"):
        write_gains(tmp_path / "g.json", PID(kp=1.0), controller="x")
    with pytest.raises(GainsFileError, match="not JSON-serializable"):
        write_gains(tmp_path / "g.json", PID(kp=1.0), thing=object())
    assert not (tmp_path / "g.json").exists()


def test_hw_never_imports_jax():
    code = "import sys, hw, hw.gains, hw.control_law; assert 'jax' not in sys.modules, 'jax'"
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    "band, words",
    [([1.2, 0.5], "low <= high"), ("0.5-1.1", "two numbers"), ([0.5], "two numbers")],
)
def test_a_prediction_edited_out_of_shape_is_refused_before_the_run(tmp_path, band, words):
    """A band reversed or written as text by hand: refused when the gains file is read (it
    was used as written, or failed after the run with a bare error); a band open above
    ("inf") is a band."""
    metrics = {"settling_time": {"nominal": 0.8, "band": band}}
    path = _write(tmp_path, _good(), prediction={"level": 0.9, "metrics": metrics})
    with pytest.raises(GainsFileError) as info:
        read_gains_file(path)
    assert info.value.field == "prediction.metrics.settling_time" and words in str(info.value)
    metrics["settling_time"]["band"] = [0.6, "inf"]
    path = _write(tmp_path, _good(), prediction={"level": 0.9, "metrics": metrics})
    assert read_gains_file(path)[1]["prediction"]["metrics"] == metrics


@pytest.mark.parametrize("spec, field", [({"settling_time": 0}, "settling_time"),
                                         ({"overshoot": -1}, "overshoot"),
                                         ({"overshoot": "5"}, "overshoot")])  # fmt: skip
def test_a_spec_edited_out_of_range_is_refused_not_replaced_by_the_lab_s(tmp_path, spec, field):
    """A spec the run would silently replace by the lab's (settling < 1 s, overshoot < 5 %)."""
    path = _write(tmp_path, _good(), spec=spec)
    with pytest.raises(GainsFileError, match="give a positive number") as info:
        read_gains_file(path)
    assert info.value.field == f"spec.{field}"
    path = _write(tmp_path, _good(), spec={"step": 0.5, "settling_time": 0.8, "horizon": None})
    assert read_gains_file(path)[1]["spec"]["settling_time"] == 0.8
