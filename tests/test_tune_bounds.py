"""`tune` says when a result sits on a bound of its search box, and checks its outputs before
computing anything (tuning/design/tune.py, tuning/commands/tune.py).

The bound flags are checked against the gains and the box directly (1 % of the bound); the
output checks run with tune() replaced by a function that fails the test if it is called.
"""

import json

import pytest

import jaxcart as jc
from jaxcart.errors import UserError
from tuning.design.result import on_bounds
from tuning.design.tune import tune


def test_on_bounds_flags_within_one_percent_of_either_bound():
    box = {"kp": (1.0, 250.0), "kd": (0.001, 50.0), "ki": (0.001, 200.0)}
    values = {"kp": 248.0, "kd": 0.00101, "ki": 3.0}
    assert on_bounds(values, ("kp", "kd", "ki"), box) == {
        "kp": ("upper", 250.0),
        "kd": ("lower", 0.001),
    }
    assert on_bounds({"kp": 246.0}, ("kp",), box) == {}  # 1.6 % below: inside
    assert on_bounds(values, ("ki",), box) == {}  # only free parameters count


@pytest.fixture(scope="module")
def short_run():
    """A short lab run (the compiled iteration is shared with tests/test_tune.py's PD run)."""
    return tune(free=("kp", "kd"), max_iterations=30, n_starts=4, patience=5)


def test_result_names_every_gain_on_a_bound(short_run):
    """Every free gain on (within 1 % of) an end of its box is flagged; on an upper end the
    cart sets (kp, kd: tuning.design.limits) the result says what sets it, on any other the
    note says how to widen the box."""
    res = short_run
    assert res.bounds["kp"][1] == pytest.approx(600.0)  # 6 V over 2 % of the 0.5 m step
    expected = {}
    for name in res.free:
        lo, hi = res.bounds[name]
        value = getattr(res.gains, name)
        if value >= 0.99 * hi:
            expected[name] = "upper"
        elif value <= 1.01 * lo:
            expected[name] = "lower"
    assert {n: side for n, (side, _) in res.on_bound.items()} == expected
    doc = res.to_json()
    assert set(doc["on_bound"]) == set(expected)
    assert doc["binding"] == res.binding and set(doc["limits"]) == {"kp", "kd"}
    json.dumps(doc, allow_nan=False)
    set_by_cart = {n for n, side in expected.items() if side == "upper" and n in res.limits}
    others = set(expected) - set_by_cart
    for name in set_by_cart:
        assert res.limits[name].what in res.binding
    if others:
        note = res.bound_note()
        assert all(n in note for n in others) and "widen" in note
    else:
        assert res.bound_note() is None


def test_command_line_prints_the_bound_and_how_to_widen_it(tmp_path, capsys, short_run):
    from tuning.commands.main import main

    summary = tmp_path / "s.json"
    args = ["tune", "--out", str(tmp_path / "g.json"), "--json", str(summary), "--quiet"]
    # kp capped at 20 V/m, far below where the design problem wants it: it must sit there.
    args += ["--free", "kp,kd", "--starts", "4", "--iterations", "30", "--bound", "kp=1,20"]
    code = main(args)
    out = capsys.readouterr().out
    doc = json.loads(summary.read_text())
    assert code in (0, 1)
    gains = json.loads((tmp_path / "g.json").read_text())
    assert doc["on_bound"]["kp"]["side"] == "upper" and doc["on_bound"]["kp"]["bound"] == 20.0
    for name, entry in doc["on_bound"].items():
        lo, hi = (1.0, 20.0) if name == "kp" else doc["bounds"][name]
        bound = hi if entry["side"] == "upper" else lo
        assert entry["bound"] == bound
        assert abs(doc["gains"][name] - bound) <= 0.01 * bound
        assert f"--bound {name}=" in out
    assert gains["on_bound"] == {
        n: {"side": e["side"], "bound": e["bound"]} for n, e in doc["on_bound"].items()
    }


@pytest.fixture
def no_tuning(monkeypatch):
    import tuning.benchmark.tuners
    import tuning.design.tune

    def refuse(*args, **kwargs):
        raise AssertionError("tune() ran although an output cannot be written")

    monkeypatch.setattr(tuning.design.tune, "tune", refuse)
    monkeypatch.setattr(tuning.benchmark.tuners, "compare_tuners", refuse)


@pytest.mark.parametrize("option", ["--out", "--json", "--plot"])
def test_unwritable_outputs_fail_before_tuning(tmp_path, capsys, no_tuning, option):
    from tuning.commands.main import main

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    names = {"--out": "g.json", "--json": "s.json", "--plot": "f.png"}
    argv = ["tune", "--out", str(tmp_path / "ok.json"), option, str(blocker / names[option])]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err and "a-file" in err
    assert not (tmp_path / "ok.json").exists()


def test_compare_json_is_checked_before_the_benchmark(tmp_path, capsys, no_tuning):
    from tuning.commands.main import main

    (tmp_path / "x").write_text("")
    assert main(["tune", "--compare", "--json", str(tmp_path / "x" / "c.json")]) == 2
    assert "--json" in capsys.readouterr().err


def test_new_parameters_are_checked():
    with pytest.raises(UserError, match="back_calculation"):
        tune(free=("kp", "kb"))
    with pytest.raises(UserError, match="bounds tau"):
        tune(free=("kp", "tau"), bounds={"tau": (0.1, 0.01)})
    with pytest.raises(UserError, match="start value tau"):
        tune(start={"kp": 40.0, "tau": -1.0})
    # A PID start keeps its own tau, kb and v_limit (the template's numbers).
    from tuning.design.problem import start_and_template

    pid = jc.PID(kp=50.0, kd=4.0, ki=1.0, tau=0.02, kb=3.0, v_limit=5.0)
    params, template = start_and_template(pid, None, ("kp",))
    assert list(params) == [50.0, 4.0, 1.0, 0.02, 3.0, 5.0] and template is pid
