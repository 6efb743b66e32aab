"""One rule for a PID's numbers (issue 20 item 3): the same bad value gets the same rule, in the
same words, from every entry point: PID(...), an experiment file's [controller], a gains file
and the tune command's options (--start for the gains). Each adds only where it came from."""

import json
import math

import numpy as np
import pytest

from hw.control_law import PID, setting_problem
from hw.expfile import ExpFileError, read_experiment_data
from hw.gains import GainsFileError, read_gains
from jaxcart.errors import UserError
from tuning.commands import options
from tuning.commands.tune import _controller, register

CSV = "t,y,r\n0,0,0.1\n0.001,0.01,0.1\n0.002,0.02,0.1\n"
HEAD = 'kind = "closed_loop"\nsample_time = 0.001\ndata = "run.csv"\n[controller]\n'

#: (setting, bad value, words of its rule that every entry point must say).
BAD = [
    ("tau", -0.01, "-0.01 s: it must be >= 0; 0 is a pure difference"),
    ("kb", -1.0, "-1.0 1/s: it must be >= 0"),
    ("v_limit", 0.0, "0.0 V: it must be positive; give the limit, e.g. 6"),
    ("v_limit", -6.0, "-6.0 V: it must be positive"),
    ("kd", math.nan, "nan V s/m: give a finite number"),
    ("tau", math.inf, "inf s: give a finite number"),
]


def _toml(value) -> str:
    return "nan" if math.isnan(value) else ("inf" if value == math.inf else repr(value))


def _experiment_error(tmp_path, name, value) -> str:
    (tmp_path / "run.csv").write_text(CSV)
    path = tmp_path / "exp.toml"
    path.write_text(HEAD + f"kp = 10.0\n{name} = {_toml(value)}\n")
    with pytest.raises(ExpFileError) as info:
        read_experiment_data(path)
    return str(info.value)


def _gains_error(tmp_path, name, value) -> GainsFileError:
    controller = PID(kp=40.0, ki=5.0, kd=5.0, v_limit=6.0).to_dict()
    controller[name] = "BIG" if value == math.inf else value
    path = tmp_path / "g.json"
    text = json.dumps({"format": "jaxcart-gains", "version": 1, "controller": controller})
    path.write_text(text.replace('"BIG"', "1e400"))  # JSON has no inf; 1e400 reads as one
    with pytest.raises(GainsFileError) as info:
        read_gains(path)
    return info.value


def _tune_args(*argv):
    import argparse

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(["tune", *argv])


@pytest.mark.parametrize("name, value, rule", BAD, ids=[f"{n}={v}" for n, v, _ in BAD])
def test_a_bad_setting_gets_one_rule_from_every_entry_point(tmp_path, name, value, rule):
    assert rule in setting_problem(name, value)
    with pytest.raises(ValueError) as info:  # the library
        PID(**{name: value})
    assert str(info.value).startswith(f"{name} = ") and rule in str(info.value)

    message = _experiment_error(tmp_path, name, value)
    assert "exp.toml" in message and f"[controller] {name} = " in message and rule in message

    if not math.isnan(value):  # JSON has no NaN: the reader refuses such a file before its fields
        err = _gains_error(tmp_path, name, value)
        assert err.field == f"controller.{name}" and rule in str(err) and "g.json" in str(err)

    flag = "--" + name.replace("_", "-")
    if name in ("kp", "ki", "kd"):
        start = {"kp": "40", "ki": "5", "kd": "5"} | {name: repr(value)}
        argv = ["--start", ",".join(start.values())]
        with pytest.raises(UserError) as info:
            options.parse_gains(argv[1], "--start")
    else:
        argv = [flag, repr(value)]
        with pytest.raises(UserError) as info:
            _controller(_tune_args(*argv))
    assert argv[0] in str(info.value) and rule in str(info.value)
    assert "\n" not in str(info.value)


SIGN = "a negative gain is positive feedback (a sign error"


@pytest.mark.parametrize("name, start", [("kp", "-40,5,5"), ("ki", "40,-5,5"), ("kd", "40,5,-5")])
def test_a_negative_gain_is_a_sign_error_where_gains_are_chosen_for_the_cart(tmp_path, name, start):
    """A gains file and tune's --start refuse it with the same line and its fix (drop the minus
    sign); a PID and an experiment file hold it, so the sign error can be simulated and flagged
    unstable before a run (jaxcart.plausibility, hw's pre-run check)."""
    value = float(start.split(",")[("kp", "ki", "kd").index(name)])
    rule = setting_problem(name, value)
    assert SIGN in rule and "drop the minus sign" in rule and ">= 0" in rule

    err = _gains_error(tmp_path, name, value)
    assert err.field == f"controller.{name}" and rule in str(err)
    with pytest.raises(UserError) as info:
        options.parse_gains(start, "--start")
    assert str(info.value) == f"--start {start}: {name} = {rule}"

    assert getattr(PID(**{name: value}), name) == value
    (tmp_path / "run.csv").write_text(CSV)
    path = tmp_path / "exp.toml"
    path.write_text(HEAD + f"{name} = {value!r}\n")
    assert getattr(read_experiment_data(path).controller, name) == value


def test_good_settings_and_array_leaves_pass():
    """The lab's settings pass everywhere; JAX/numpy array leaves (the tuner's traced gains)
    are not checked by PID, as a traced value cannot be compared."""
    for name, value in PID(kp=40.0, ki=5.0, kd=5.0, v_limit=6.0).to_dict().items():
        if name not in ("derivative_on", "anti_windup"):
            assert setting_problem(name, value) is None, name
    assert setting_problem("v_limit", math.inf) is None
    assert setting_problem("tau", 0) is None and setting_problem("kp", np.float32(2.0)) is None
    assert "give a number in V/m" in setting_problem("kp", "40")
    assert "give a number" in setting_problem("kp", True)
    assert PID(kp=np.array([-1.0, math.nan])).kp.shape == (2,)
