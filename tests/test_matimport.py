"""Raw QUARC/Simulink .mat files in, without a hand-written TOML (issue 22 item 1): every scope
layout (structure with time, structure with empty time, N x 2 arrays, muxed scopes by column
or label, MATLAB v7.3/HDF5), the recorded error e = r - y through the reference, and each
recording's experiment recognised from its content and names, with a question where the
evidence is weak."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from jaxcart import matfile, matimport
from jaxcart.errors import UserError
from jaxcart.files import read_experiment

Q = 2.2735e-5  # the lab's encoder [m/count]


def _scope(values, time=None, label="", block="model/scope"):
    """A Simulink scope structure as savemat writes a MATLAB struct (time empty: 'Structure')."""
    values = np.asarray(values, dtype=float)
    values = values.reshape(values.shape[0], -1)
    signals = {"values": values, "dimensions": float(values.shape[1]), "label": label}
    t = np.zeros((0, 0)) if time is None else np.asarray(time, dtype=float).reshape(-1, 1)
    return {"time": t, "signals": signals, "blockName": block}


def _p50(n=2000, ts=0.001):
    """A P 50 step of 0.4 m with a 6 V limit: positions in whole counts, v = 50 (0.4 - y)."""
    t = np.arange(n) * ts
    y = np.rint(0.397 * (1 - np.exp(-t / 0.25)) ** 2 / Q) * Q
    return t, y, np.clip(50.0 * (0.4 - y), -6.0, 6.0)


# ---------------------------------------------------------------- layouts


def test_muxed_scope_column_by_number_and_label(tmp_path):
    t, y, v = _p50()
    r = np.full(t.shape, 0.4)
    scipy.io.savemat(
        tmp_path / "mux.mat",
        {
            "scope": _scope(np.column_stack([y, v]), t, label="<cart position>,<voltage>"),
            "arr": np.column_stack([t, y, r]),  # Simulink's Array: time, then the signals
        },
    )
    toml = tmp_path / "mux.toml"
    for y_src, v_src in (("scope[1]", "scope[2]"), ("scope[cart position]", "scope[voltage]")):
        toml.write_text(
            'kind = "closed_loop"\n[data]\n'
            f'y = "mux.mat:{y_src}"\nv = "mux.mat:{v_src}"\nr = "mux.mat:arr[2]"\n'
            "[controller]\nkp = 50.0\nv_limit = 6.0\n"
        )
        rec = read_experiment(toml, check=False)
        np.testing.assert_array_equal(rec.position, y)
        np.testing.assert_array_equal(rec.command, v)
        np.testing.assert_array_equal(rec.reference, r)
        np.testing.assert_array_equal(rec.time, t)
    toml.write_text('kind = "tap"\n[data]\ny = "mux.mat:scope"\n')
    with pytest.raises(UserError, match=r"holds 2 signals .*'cart position'.*scope\[1\]"):
        read_experiment(toml)
    toml.write_text('kind = "tap"\n[data]\ny = "mux.mat:scope[3]"\n')
    with pytest.raises(UserError, match=r"choose 1 \.\.\. 2"):
        read_experiment(toml)
    toml.write_text('kind = "tap"\n[data]\ny = "mux.mat:scope[speed]"\n')
    with pytest.raises(UserError, match="no single signal labelled so"):
        read_experiment(toml)


def test_scope_with_several_inputs_is_a_struct_array(tmp_path):
    """A scope with two input ports saves signals as a 1 x 2 struct array, each labelled."""
    t, y, v = _p50(500)
    signals = np.empty(
        (1, 2), dtype=[("values", object), ("dimensions", object), ("label", object)]
    )
    signals[0, 0] = (y[:, None], 1.0, "position")
    signals[0, 1] = (v[:, None], 1.0, "voltage")
    scope = {"time": t[:, None], "signals": signals, "blockName": "lab/Scope"}
    scipy.io.savemat(tmp_path / "two.mat", {"ScopeData": scope})
    found = matimport.read_signals(tmp_path / "two.mat")
    assert [(s.source, s.role) for s in found] == [
        ("two.mat:ScopeData[1]", "y"),
        ("two.mat:ScopeData[2]", "v"),
    ]
    np.testing.assert_array_equal(found[1].values, v)
    np.testing.assert_array_equal(found[0].time, t)


def _write_v73(path, variables):
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 behind a 512-byte MAT header, arrays
    transposed (column-major), structs as groups with MATLAB_class attributes, text as uint16,
    an empty array as its dimensions with MATLAB_empty."""
    import h5py

    def put(parent, name, value):
        if isinstance(value, dict):
            group = parent.create_group(name)
            group.attrs["MATLAB_class"] = np.bytes_("struct")
            for key, item in value.items():
                put(group, key, item)
        elif isinstance(value, str):
            ds = parent.create_dataset(name, data=np.array([[ord(c)] for c in value], np.uint16))
            ds.attrs["MATLAB_class"] = np.bytes_("char")
        else:
            arr = np.asarray(value, dtype=float)
            if arr.size == 0:
                ds = parent.create_dataset(name, data=np.array(arr.shape, dtype=np.uint64))
                ds.attrs["MATLAB_empty"] = np.uint8(1)
            else:
                ds = parent.create_dataset(name, data=np.atleast_2d(arr).T)
            ds.attrs["MATLAB_class"] = np.bytes_("double")

    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            put(f, name, value)
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: jaxcart test HDF5 schema 1.00 ."
    with open(path, "r+b") as f:
        f.write(header.ljust(116) + b"\0" * 8 + b"\x00\x02IM")


def test_v73_hdf5_reads_as_v7(tmp_path):
    t, y, v = _p50(800)
    part = {
        "y": {
            "time": np.zeros((0, 0)),
            "signals": {"values": y[:, None], "dimensions": 1.0, "label": ""},
            "blockName": "labcartsat/cart position",
        },
        "v": {
            "time": t[:, None],
            "signals": {"values": v[:, None], "dimensions": 1.0, "label": "voltage"},
            "blockName": "labcartsat/voltage out",
        },
        "arr": np.column_stack([t, y]),
    }
    _write_v73(tmp_path / "run73.mat", part)
    with pytest.raises(NotImplementedError):  # scipy alone refuses it: h5py reads it
        scipy.io.loadmat(tmp_path / "run73.mat")
    loaded = matfile.load_mat(tmp_path / "run73.mat")
    assert matfile.classify(loaded["y"]) == "structure"
    assert matfile.classify(loaded["v"]) == "structure-with-time"
    assert matfile.classify(loaded["arr"]) == "array"
    assert loaded["y"].blockName == "labcartsat/cart position"
    (tmp_path / "run.toml").write_text(
        'kind = "closed_loop"\n[data]\ny = "run73.mat:y"\nv = "run73.mat:v"\n'
        "[controller]\nkp = 50.0\nv_limit = 6.0\n[reference]\nkind = 'step'\namplitude = 0.4\n"
    )
    rec = read_experiment(tmp_path / "run.toml", check=False)
    np.testing.assert_array_equal(rec.position, y)
    np.testing.assert_array_equal(rec.command, v)
    np.testing.assert_array_equal(rec.time, t)
    np.testing.assert_array_equal(
        matfile.scope_signals(loaded["arr"], "arr")[0].values, y
    )  # N x 2 [t, value], transposed back
    # No TOML: y and arr hold the same position in two layouts, one signal (arr's time).
    (run,) = matimport.scan([tmp_path / "run73.mat"])
    assert run.problem is None and run.signals["y"].source == "run73.mat:arr"
    assert [(a.source, b.source) for a, b in run.copies] == [("run73.mat:arr", "run73.mat:y")]
    np.testing.assert_array_equal(read_experiment(tmp_path / "run73.mat").position, y)
    _write_v73(tmp_path / "raw73.mat", {"y": part["y"], "v": part["v"]})
    raw = read_experiment(tmp_path / "raw73.mat")  # no TOML: recognised
    assert raw.controller.kp == 50.0 and raw.controller.v_limit == 6.0
    np.testing.assert_array_equal(raw.reference, np.full(y.shape, 0.4))


# ---------------------------------------------------------------- the recorded error


def test_error_stands_for_the_position_through_the_reference(tmp_path):
    t, y, v = _p50(600)
    e = 0.4 - y
    (tmp_path / "err.csv").write_text(
        "t,e,v\n"
        + "".join(f"{a!r},{b!r},{c!r}\n" for a, b, c in np.column_stack([t, e, v]).tolist())
    )
    toml = tmp_path / "err.toml"
    toml.write_text(
        'kind = "closed_loop"\ndata = "err.csv"\n[controller]\nkp = 50.0\nv_limit = 6.0\n'
        '[reference]\nkind = "step"\namplitude = 0.4\n'
    )
    rec = read_experiment(toml, check=False)
    np.testing.assert_allclose(rec.position, y, atol=1e-15)  # y = r - e, to rounding
    scipy.io.savemat(tmp_path / "both.mat", {"y": y[:, None], "Error": e[:, None]})
    toml.write_text(
        'kind = "closed_loop"\nsample_time = 0.001\n[data]\ny = "both.mat:y"\n'
        'e = "both.mat:Error"\n[controller]\nkp = 50.0\nv_limit = 6.0\n'
    )
    rec = read_experiment(toml, check=False)  # no [reference]: r = y + e
    np.testing.assert_allclose(rec.reference, np.full(y.shape, 0.4), atol=1e-15)
    toml.write_text('kind = "closed_loop"\nsample_time = 0.001\n[data]\ne = "both.mat:Error"\n')
    with pytest.raises(UserError, match=r"without a position y: give the reference"):
        read_experiment(toml)
    toml.write_text('kind = "tap"\nsample_time = 0.001\n[data]\ne = "both.mat:Error"\n')
    with pytest.raises(UserError, match="an error needs a reference"):
        read_experiment(toml)


# ---------------------------------------------------------------- recognition


@pytest.fixture(scope="module")
def builtin():
    """The built-in recordings (synthetic, from a cart unlike the handout's model)."""
    from tuning.lab.data import builtin_dir

    folder = builtin_dir()
    stems = ("tap", "p50", "ramp", "p10", "pi", "pid")
    return {s: read_experiment(folder / f"{s}.toml", check=False) for s in stems}


@pytest.mark.parametrize(
    ("stem", "layout", "want"),
    [
        ("tap", "array", "tap"),
        ("p50", "structure", "p_step"),
        ("ramp", "structure-with-time", "ramp"),
        ("p10", "array", "p_error"),
        ("pi", "structure", "pi"),
        ("pid", "structure-with-time", "pid"),
    ],
)
def test_each_experiment_recognised_from_content_alone(builtin, tmp_path, stem, layout, want):
    """Saved as scopes under names that say nothing (run.mat, variables a and b): the content
    alone tells the experiment, and the settings it implies are the ones that ran."""
    rec = builtin[stem]
    t, y = rec.time, rec.position
    v = rec.command if stem != "ramp" else 0.1 * t  # the built-in ramp keeps no column v
    pack = {"array": lambda x: np.column_stack([t, x]), "structure": _scope}
    pack["structure-with-time"] = lambda x: _scope(x, t)
    variables = {"a": pack[layout](y)}
    if v is not None:
        variables["b"] = pack[layout](v)
    scipy.io.savemat(tmp_path / "run.mat", variables)
    (found,) = matimport.scan([tmp_path / "run.mat"])
    assert [s.role for s in found.signals.values()] == ["y", "v"][: len(variables)]
    guess = found.guess
    assert guess.experiment == want and guess.confident, guess.lines()
    got = read_experiment(tmp_path / "run.mat", check=False)
    np.testing.assert_array_equal(got.position, y)
    if want == "tap":
        assert got.kind == "tap" and got.controller is None
    elif want == "ramp":
        assert got.kind == "open_loop" and guess.ramp == 0.1
    else:
        ran = rec.controller
        # The gains the voltage shows: exact for P and PI; the PID's ki (0.94 V/(m s), under
        # 0.2 V over the run) within 5 %, kp and kd within 0.1 %.
        assert got.controller.kp == pytest.approx(ran.kp, rel=1e-3)
        assert got.controller.kd == pytest.approx(ran.kd, rel=1e-3)
        assert got.controller.ki == pytest.approx(ran.ki, rel=0.05, abs=1e-9)
        assert got.controller.v_limit == ran.v_limit
        np.testing.assert_array_equal(got.reference, rec.reference)  # the step, exactly


@pytest.mark.parametrize(
    ("stem", "want", "why"),
    [
        ("pi", "pi", "then moves again toward e = 0 .* integral action"),
        ("p10", "p_error", "no integral action .* P 10's Coulomb dead band"),
    ],
)
def test_error_scope_alone_tells_p10_from_pi(builtin, tmp_path, stem, want, why):
    """Parts (iii) and (iv) save the error e = r - y. Without the voltage the physics tells
    them apart: under P control a cart at rest stays at rest, inside the dead band |e| <=
    f_c/(k gamma), while a PI's integral grows until the cart moves again toward e = 0."""
    rec = builtin[stem]
    e = rec.reference - rec.position
    scipy.io.savemat(tmp_path / "scope3.mat", {"Error": np.column_stack([rec.time, e])})
    (run,) = matimport.scan([tmp_path / "scope3.mat"])
    assert run.guess.experiment == want and run.guess.confident, run.lines()
    assert any(re.search(why, x.text) and x.weight == 3 for x in run.guess.evidence)
    got = read_experiment(tmp_path / "scope3.mat", check=False)
    assert got.controller == rec.controller  # the handout's, no voltage to measure it
    np.testing.assert_allclose(got.position, rec.position, atol=1e-15)  # y = r - e


@pytest.mark.parametrize(("f_c", "B_eq"), [(0.3, 1.5), (0.45, 4.6), (0.6, 1.5)])
def test_error_alone_recognised_on_other_carts(f_c, B_eq):
    """P 10 and PI runs (step 0.2 m, 8 s) on carts unlike the built-in one, with stiction
    (f_s = 1.8 f_c): the error alone, and with the position, names each."""
    import jax

    import jaxcart as jc
    from jaxcart.plantspec import build_plant
    from jaxcart.recognition import Traces, recognise
    from jaxcart.synthetic import make_recording

    plant = build_plant({"B_eq": B_eq, "f_c": f_c, "f_s": 1.8 * f_c, "v_sat": 6.0})
    for pid, want in ((jc.PID(kp=10.0), "p_error"), (jc.PID(kp=10.0, ki=15.0), "pi")):
        with jax.enable_x64(True):
            rec = make_recording(plant, pid, jc.step(0.2, horizon=8.0), seed=7)
        e = rec.reference - rec.position
        for traces in (Traces(0.001, error=e), Traces(0.001, position=rec.position, error=e)):
            guess = recognise(traces)
            assert (guess.experiment, guess.confident) == (want, True), guess.lines()


def test_error_that_has_not_settled_asks_unless_named(builtin, tmp_path):
    """The PI's error cut off while the cart still moves shows neither integral action nor a
    dead band: weak evidence, one line that asks; the part named (option or file name)
    settles it."""
    rec = builtin["pi"]
    e = (rec.reference - rec.position)[:1200]
    scipy.io.savemat(tmp_path / "scope3.mat", {"Error": np.column_stack([rec.time[:1200], e])})
    with pytest.raises(UserError, match=r"^scope3\.mat: the evidence is weak .*--as PART") as err:
        read_experiment(tmp_path / "scope3.mat")
    assert "\n" not in str(err.value)
    got = read_experiment(tmp_path / "scope3.mat", experiment="pi", check=False)
    assert got.controller.kp == 10.0 and got.controller.ki == 15.0  # the handout's PI
    shutil.copy(tmp_path / "scope3.mat", tmp_path / "part4_error.mat")
    named = read_experiment(tmp_path / "part4_error.mat", check=False)  # "part4": Part (iv)
    assert named.controller.ki == 15.0


def test_position_chosen_in_a_muxed_scope_on_the_command_line(tmp_path):
    t, y, v = _p50(1500)
    other = np.rint(0.5 * y / Q) * Q  # a second cart's position, also in counts
    mux = _scope(np.column_stack([other, v, y]), t)
    scipy.io.savemat(tmp_path / "mux.mat", {"ScopeData": mux})
    with pytest.raises(UserError, match=r"2 different signals look like a position \(mux.mat:Scop"):
        read_experiment(tmp_path / "mux.mat")
    got = read_experiment(f"{tmp_path / 'mux.mat'}:ScopeData[3]", check=False)
    np.testing.assert_array_equal(got.position, y)
    assert got.controller.kp == 50.0  # the unlabelled column 2 is the voltage: P 50
    with pytest.raises(UserError, match=r"choose 1 \.\.\. 3"):
        read_experiment(f"{tmp_path / 'mux.mat'}:ScopeData[4]")


# ---------------------------------------------------------------- the lab's real files


@pytest.fixture
def real_folder(realdata, tmp_path):
    """The lab's real .mat files as QUARC saved them into one folder, names included, and
    nothing else (the shared folder keeps the Part (v) and repeat runs in sub-folders)."""
    real = Path(realdata)
    folder = tmp_path / "data"
    folder.mkdir()
    for path in [*sorted(real.glob("*.mat")), real / "pd" / "5.1wksp_1.mat"]:
        shutil.copyfile(path, folder / path.name)
    shutil.copyfile(real / "repeat" / "p50_repeat.mat", folder / "p50_repeat.mat")
    return folder


def test_real_pd_workspace_holds_one_position(real_folder, realdata):
    """The Part (v) workspace saves the position twice (Cartposition, y: the same values and
    time) and the pendulum rod's sensor (ScopeData1, block 'labcartpid/rod': whole counts of
    1.5e-3, not the cart's encoder): one position, the rod not used, and the controller the
    voltage shows is the stated PD (realdata/pd/pd.toml: kp = 55, kd = 5, a pure difference)."""
    (run,) = matimport.scan([real_folder / "5.1wksp_1.mat"])
    assert run.problem is None and run.usable()
    assert {k: s.source.split(":")[1] for k, s in run.signals.items()} == {
        "y": "Cartposition",
        "e": "e",
        "v": "v",
    }
    assert [(a.source, b.source) for a, b in run.copies] == [
        ("5.1wksp_1.mat:Cartposition", "5.1wksp_1.mat:y")
    ]
    assert [s.source for s in run.ignored] == ["5.1wksp_1.mat:ScopeData1"]
    assert any("5.1wksp_1.mat:y is a copy of 5.1wksp_1.mat:Cartposition" in x for x in run.lines())
    assert run.guess.experiment == "pid" and "a PD" in run.guess.evidence[1].text
    got = read_experiment(real_folder / "5.1wksp_1.mat")
    stated = read_experiment(Path(realdata) / "pd" / "pd.toml")
    assert got.controller == stated.controller  # kp 55, kd 5, tau 0, v_limit 6, exactly
    np.testing.assert_array_equal(got.position, stated.position)
    np.testing.assert_array_equal(got.reference, stated.reference)  # r = y + e = 0.5 m
    # Without the name, the rod is still no position: its counts are not the cart's.
    rod = matimport.read_signals(real_folder / "5.1wksp_1.mat")
    assert [s.role for s in rod if s.source.endswith("ScopeData1")] == ["?"]


def test_copies_in_other_layouts_and_times_are_one_signal(tmp_path):
    """A position saved as an N x 2 array, again as a structure with its time 5 s later and
    again without time, and the voltage twice: one signal each; two different positions are
    still a question, one line with the fix."""
    t, y, v = _p50(900)
    scipy.io.savemat(
        tmp_path / "ws.mat",
        {
            "Cartposition": np.column_stack([t, y]),
            "ScopeData": _scope(y, t + 5.0, block="lab/cart position"),
            "y": _scope(y),
            "v": _scope(v, t),
            "u": v,
        },
    )
    (run,) = matimport.scan([tmp_path / "ws.mat"])
    assert run.problem is None and run.guess.experiment == "p_step" and run.usable()
    assert sorted(b.source.split(":")[1] for _, b in run.copies) == ["ScopeData", "u", "y"]
    got = read_experiment(tmp_path / "ws.mat")
    np.testing.assert_array_equal(got.position, y)
    np.testing.assert_array_equal(got.time, t)  # the first copy's time
    scipy.io.savemat(tmp_path / "two.mat", {"a": np.column_stack([t, y]), "b": _scope(y + Q, t)})
    with pytest.raises(UserError) as err:
        read_experiment(tmp_path / "two.mat")
    assert str(err.value) == (
        "two.mat: 2 different signals look like a position (two.mat:a, two.mat:b); choose "
        "the one to use: jaxcart import two.mat:a (or map it in an experiment file's [data] "
        "table)"
    )


def _pi_scopes(n=3000, ts=0.001, r=0.4):
    """A PI step's position and error (e = r - y) in whole counts, the cart at rest at 0."""
    t = np.arange(n) * ts
    y = np.rint(r * (1 - np.exp(-t / 0.4)) / Q) * Q
    return t, y, r - y


def test_a_workspace_of_two_runs_is_two_runs(tmp_path, capsys):
    """A workspace saved after two experiments (the real cart's lab1_4.1.mat: the P 50 step's
    Cartposition and v from model labcartsat, 3135 samples, beside the PI step's y, e and
    Error from labcartcolint, 6200): two runs, each named by its model, each its own
    experiment file; reading the file alone says which runs it holds and how to choose one,
    and choosing a run's position reads that run."""
    from tuning.commands.main import main

    t, y, v = _p50(900)
    tp, yp, ep = _pi_scopes(1500)
    scipy.io.savemat(
        tmp_path / "lab1_4.1.mat",
        {
            "Cartposition": _scope(y, t, block="labcartsat/cart"),
            "v": _scope(v, block="labcartsat/voltage out"),
            "y": _scope(yp, block="labcartcolint/cart position"),
            "e": _scope(ep, block="labcartcolint/error out"),
            "Error": _scope(ep, tp, block="labcartcolint/error"),
        },
    )
    runs = matimport.scan([tmp_path / "lab1_4.1.mat"])
    assert [(r.part, r.problem) for r in runs] == [("labcartsat", None), ("labcartcolint", None)]
    p50, pi = runs
    assert pi.signals["y"].source == "lab1_4.1.mat:y" and "v" not in pi.signals
    assert p50.signals["y"].source == "lab1_4.1.mat:Cartposition" and "e" not in p50.signals
    assert p50.guess.experiment == "p_step" and p50.usable()
    assert (pi.stem, p50.stem) == ("lab1_4.1-labcartcolint", "lab1_4.1-labcartsat")
    with pytest.raises(UserError) as err:
        read_experiment(tmp_path / "lab1_4.1.mat")
    text = str(err.value)
    assert "holds 2 runs (labcartsat: lab1_4.1.mat:Cartposition (P control k = 50" in text
    assert "; labcartcolint: lab1_4.1.mat:y" in text and "\n" not in text
    got = read_experiment(f"{tmp_path / 'lab1_4.1.mat'}:Cartposition")
    np.testing.assert_array_equal(got.position, y)
    assert got.command is not None and got.controller.kp == 50.0
    pi_run = read_experiment(f"{tmp_path / 'lab1_4.1.mat'}:y")
    np.testing.assert_array_equal(pi_run.position, yp)
    assert pi_run.reference[0] == pytest.approx(0.4) and pi_run.command is None
    # One file, two runs, each read as the lab reads them: named by the position chosen, as
    # read_experiment names them (two names in a fit's tables and the lab's lines); both may
    # be fitted together, one run twice may not, named alike or not.
    from jaxcart.files import read_imported
    from jaxcart.plausibility import check_distinct

    a, b = (read_imported(r, quiet=True) for r in runs)
    assert Path(a.path).name == "lab1_4.1.mat:Cartposition" and a.path == got.path
    assert Path(b.path).name == "lab1_4.1.mat:y" == Path(pi_run.path).name
    check_distinct([a, b])
    check_distinct([read_imported(runs[0], tmp_path / "lab1_4.1.mat", quiet=True), b])
    with pytest.raises(UserError, match="are identical samples"):
        check_distinct([b, read_imported(runs[1], quiet=True)])
    assert Path(pi_run.path).name == "lab1_4.1.mat:y"  # a chosen run: its name in a fit
    # The command writes each run's experiment file, named by its model.
    out = tmp_path / "out"
    assert main(["--no-cache", "import", str(tmp_path / "lab1_4.1.mat"), "--out", str(out)]) == 0
    assert "lab1_4.1.mat (labcartsat):" in capsys.readouterr().out
    made = read_experiment(out / "lab1_4.1-labcartsat.toml")
    np.testing.assert_array_equal(made.position, y)
    # Named without saying which run (import --as, lab.toml): a question, not the first run.
    for run in matimport.scan([tmp_path / "lab1_4.1.mat"], named={"lab1_4.1.mat": "pi"}):
        assert run.problem.startswith("lab1_4.1.mat holds 2 runs (labcartsat, labcartcolint)")
    (run,) = matimport.scan(
        [tmp_path / "lab1_4.1.mat"], named={"lab1_4.1.mat": "pi"}, chosen={"lab1_4.1.mat": "y"}
    )
    assert run.part == "labcartcolint" and run.guess.experiment == "pi" and run.problem is None
    # The error chosen stays the error, and its run's position the position.
    (run,) = matimport.scan([tmp_path / "lab1_4.1.mat"], chosen={"lab1_4.1.mat": "Error"})
    assert run.signals["y"].source == "lab1_4.1.mat:y" and run.signals["e"].source.endswith("Error")
    # A part that is no run says why, in the one line.
    scipy.io.savemat(
        tmp_path / "bad.mat",
        {
            "Cartposition": _scope(y, t, block="labcartsat/cart"),
            "y2": _scope(y + 3 * Q, t, block="labcartsat/cart"),
            "y": _scope(yp, block="labcartcolint/cart position"),
        },
    )
    with pytest.raises(
        UserError, match=r"holds 2 runs \(labcartsat: bad.mat: 2 different signals look like a pos"
    ):
        read_experiment(tmp_path / "bad.mat")
    # lab.toml names a run of the file by its position; the file alone is the question.
    from tuning.lab.inputs import find_inputs

    lab = tmp_path / "lab"
    lab.mkdir()
    shutil.copy(tmp_path / "lab1_4.1.mat", lab)
    (lab / "lab.toml").write_text('[recordings]\npi = "lab1_4.1.mat:y"\n')
    found = find_inputs(lab)
    np.testing.assert_array_equal(found.recordings["pi"].position, yp)
    np.testing.assert_array_equal(found.recordings["pi"].reference, pi_run.reference)
    (lab / "lab.toml").write_text('[recordings]\npi = "lab1_4.1.mat"\n')
    with pytest.raises(UserError, match="name the one you mean .*, e.g. lab1_4.1.mat:"):
        find_inputs(lab)
    # Found without lab.toml, each run goes to its part, named apart: the diagnosis table's
    # rows find their parts by these names (both runs were lab1_4.1.mat, and both rows took
    # the first part found).
    from types import SimpleNamespace

    from tuning.lab.diagnosis import _part_of

    (lab / "lab.toml").unlink()
    found = find_inputs(lab)
    names = {slot: Path(r.path).name for slot, r in found.recordings.items()}
    assert names == {"p_step": "lab1_4.1.mat:Cartposition", "pi": "lab1_4.1.mat:y"}
    assert _part_of(SimpleNamespace(inputs=found), "lab1_4.1.mat:y") == "(iv) PI"
    # A run of the workspace offered for a part lab.toml gives another file: the lab.toml
    # written beside the report names it by its position.
    from tuning.lab.inputs import write_used

    shutil.copy(lab / "lab1_4.1.mat", lab / "copy.mat")
    (lab / "lab.toml").write_text('[recordings]\np_step = "copy.mat:Cartposition"\n')
    found = find_inputs(lab)
    assert [(s, r.part) for s, r, _ in found.offers] == [("p_step", "labcartsat")]
    (tmp_path / "report").mkdir()
    write_used(found, tmp_path / "report", lab)
    assert (
        '# p_step = "lab1_4.1.mat:Cartposition"' in (tmp_path / "report" / "lab.toml").read_text()
    )
    # Headers with a slash are no Simulink blocks: a CSV is one run.
    _csv(tmp_path / "slash.csv", "position / m,error / m", y, 0.4 - y)
    assert [r.part for r in matimport.scan([tmp_path / "slash.csv"])] == [None]
    # Two positions of one length and one model stay a question (two.mat above).


def test_a_rest_then_a_slow_creep_toward_zero_is_integral_action(tmp_path):
    """The real cart's PI step (lab1_4.1.mat's y and e, in a file whose name says nothing):
    after its overshoot it rests 0.7 s at e = 19.2 mm, then creeps on to 6 mm at about 7 mm/s,
    too slowly to count as a move; under P control a cart at rest stays at rest, so this is
    integral action (strong), where it was read as P 50's dead band and asked about."""
    ts = 0.001
    t = np.arange(6200) * ts
    fall = 0.0192 + (0.4 - 0.0192) * np.exp(-t / 0.4) * np.cos(2.0 * t)  # to 19.2 mm by 3.4 s
    e = np.where(t < 3.4, fall, 0.0192)
    e = np.where(t > 4.1, np.maximum(0.0192 - 0.0066 * (t - 4.1), 0.006), e)
    e = np.rint(e / Q) * Q
    scipy.io.savemat(tmp_path / "run7.mat", {"y": _scope(0.4 - e), "e": _scope(e)})
    (run,) = matimport.scan([tmp_path / "run7.mat"])
    assert run.guess.experiment == "pi" and run.guess.confident, run.lines()
    (creep,) = [x for x in run.guess.evidence if "creeps on toward e = 0" in x.text]
    assert creep.weight == 3 and "rests 0.701 s at e = 19.2 mm" in creep.text


def test_an_error_scope_that_starts_near_zero_under_integral_action_is_warned(tmp_path):
    """An error scope alone of a PI run whose first error is 4.3 mm, far below the handout's
    0.2 m step (the real cart's 4.1e.mat: the last 7.7 s of a run, the same samples as
    4.1err.mat whose time starts at t = 15 s): read as a step of 4.3 mm from rest, with a
    warning that a scope started after the step carries a built-up integral; the error that
    creeps 5 mm without a fast move is said to change; the lab leaves the run out. The same
    scope from the step has no warning (named PI: its error alone looks like P 10's)."""
    n = 4000
    creep = np.rint((0.0043 - 0.0052 * np.clip(np.arange(n) / n - 0.3, 0, None) / 0.7) / Q) * Q
    scipy.io.savemat(tmp_path / "4.1e.mat", {"e": _scope(creep, block="labcartcolint/error out")})
    (run,) = matimport.scan([tmp_path / "4.1e.mat"])
    assert run.guess.experiment == "pi"
    text = "\n".join(run.lines())
    assert "the cart creeps or rests" in text and "does not move" not in text
    note = run.meta()["notes"]["late_start"]  # in the experiment file: every reader warns
    assert note.startswith("the error starts at 4.3 mm, not at a step like the handout's 0.2 m")
    assert "the integral (ki = 15 V/(m s)) had built up" in note
    rec = read_experiment(tmp_path / "4.1e.mat")
    assert any(note in w for w in rec.warnings)
    _, _, e = _pi_scopes(n, r=0.2)
    scipy.io.savemat(tmp_path / "4.1s.mat", {"e": _scope(e, block="labcartcolint/error out")})
    (run,) = matimport.scan([tmp_path / "4.1s.mat"], named={"4.1s.mat": "pi"})
    assert run.guess.experiment == "pi" and "late_start" not in run.meta()["notes"]
    rec = read_experiment(tmp_path / "4.1s.mat", experiment="pi")
    assert not any("the error starts at" in w for w in rec.warnings)
    # A small step from rest (40 mm, under a quarter of the handout's) sets off at once: no note.
    _, _, e = _pi_scopes(n, r=0.04)
    scipy.io.savemat(tmp_path / "4.1m.mat", {"e": _scope(e, block="labcartcolint/error out")})
    (run,) = matimport.scan([tmp_path / "4.1m.mat"], named={"4.1m.mat": "pi"})
    assert "late_start" not in run.meta()["notes"]
    # The lab leaves such a run out of Part (iv) and the cart's fit, and says why.
    from tuning.lab.inputs import find_inputs

    lab = tmp_path / "lab"
    lab.mkdir()
    shutil.copy(tmp_path / "4.1e.mat", lab)
    t, y, v = _p50(900)
    scipy.io.savemat(lab / "2.1.mat", {"y": _scope(y, t), "v": _scope(v, t)})
    inputs = find_inputs(lab)
    assert set(inputs.recordings) == {"p_step"}
    (why,) = [w for name, w in inputs.unused if name == "4.1e.mat"]
    assert why.startswith("the error starts at 4.3 mm") and why.endswith("name it in lab.toml")


def test_a_non_finite_sample_is_one_line_not_a_traceback(tmp_path, capsys):
    from tuning.commands.main import main

    t, y, v = _p50(500)
    v[100] = np.nan
    scipy.io.savemat(tmp_path / "n.mat", {"y": _scope(y, t), "v": _scope(v, t)})
    assert main(["--no-cache", "import", str(tmp_path / "n.mat")]) == 2
    out = capsys.readouterr().out
    assert "  n.mat:v holds nan at sample 101 (1 such); every sample must be a finite number" in out
    assert "Traceback" not in out and not (tmp_path / "n.toml").exists()


def test_real_lab_files_assigned_and_lab_toml_reproduces(real_folder, tmp_path):
    from tuning.lab.inputs import find_inputs, write_used

    runs = {r.label: r for r in matimport.scan(sorted(real_folder.glob("*.mat")))}
    assert {k: (r.experiment, r.guess.confident) for k, r in runs.items()} == {
        "part1.1.mat": ("tap", True),
        "2.1pos.mat + 2.1volt.mat": ("p_step", True),
        "5.1wksp_1.mat": ("pid", True),
        "p50_repeat.mat": ("p_step", True),
    }
    inputs = find_inputs(real_folder)
    assert {s: Path(r.path).name for s, r in inputs.recordings.items()} == {
        "tap": "part1.1.mat",
        "p_step": "2.1pos.mat",
        "pid": "5.1wksp_1.mat",
    }
    # Part (ii) again: the first by name is the part's, the other a repeat (the joint fit's).
    assert {s: [Path(r.path).name for r in rs] for s, rs in inputs.repeats.items()} == {
        "p_step": ["p50_repeat.mat"]
    }
    assert "chosen over p50_repeat.mat as the first by name" in inputs.how["p_step"]
    assert inputs.unused == []
    p50 = inputs.recordings["p_step"]
    assert p50.controller.kp == 50.0 and p50.controller.v_limit == 6.0
    assert np.all(p50.reference == 0.4) and p50.sample_time == 0.001
    assert inputs.recordings["tap"].kind == "tap"
    report = tmp_path / "report"
    report.mkdir()
    written = write_used(inputs, report)
    assert sorted(str(p.relative_to(report)) for p in written) == [
        "2.1pos.toml",
        "5.1wksp_1.toml",
        "lab.toml",
        "part1.1.toml",
        "repeat/p50_repeat.toml",
    ]
    again = find_inputs(report)  # the lab.toml written reproduces the assignment and data
    assert set(again.recordings) == set(inputs.recordings)
    for slot, rec in inputs.recordings.items():
        other = again.recordings[slot]
        assert other.kind == rec.kind and other.controller == rec.controller
        assert other.sample_time == rec.sample_time
        np.testing.assert_array_equal(other.position, rec.position)
        np.testing.assert_array_equal(other.signal64(), rec.signal64())
        assert again.how[slot] == "named in lab.toml"
    (repeat,) = again.repeats["p_step"]
    np.testing.assert_array_equal(repeat.position, inputs.repeats["p_step"][0].position)
    # One line corrected: the repeat run instead (the written file offers it, commented).
    index = report / "lab.toml"
    lines = index.read_text().splitlines()
    offer = next(x for x in lines if x.startswith("# p_step = "))
    lines = [x for x in lines if not x.startswith("p_step = ")]
    lines[lines.index(offer)] = offer[2:]
    index.write_text("\n".join(lines) + "\n")
    swapped = find_inputs(report)
    assert Path(swapped.recordings["p_step"].path).name == "p50_repeat.mat"
    assert swapped.recordings["p_step"].n_samples == 3135


def _student_scopes(folder):
    """The parts the real folder lacks, saved as a student's scopes would save them, made by
    jaxcart.synthetic on a cart like the real one: the 0.1 V/s ramp as 3.1pos.mat + 3.1volt.mat
    (structures without time, like 2.1pos/2.1volt), P 10 as run3.mat (Cartposition N x 2 and
    the voltage u with time) and PI as run4.mat with only y and e (structures with time)."""
    import jax

    import jaxcart as jc
    from jaxcart.plantspec import build_plant
    from jaxcart.synthetic import make_recording

    cart = build_plant({"B_eq": 1.6, "f_c": 0.44, "v_sat": 6.0})
    with jax.enable_x64(True):
        ramp = make_recording(cart, None, jc.voltage_ramp(0.1, horizon=6.0), seed=1)
        p10 = make_recording(cart, jc.PID(kp=10.0), jc.step(0.2, horizon=8.0), seed=2)
        pi = make_recording(cart, jc.PID(kp=10.0, ki=15.0), jc.step(0.2, horizon=10.0), seed=3)
    block = "labcartol/cart position"
    scipy.io.savemat(folder / "3.1pos.mat", {"y": _scope(ramp.position, block=block)})
    block = "labcartol/voltage out"
    scipy.io.savemat(folder / "3.1volt.mat", {"v": _scope(ramp.command, block=block)})
    scipy.io.savemat(
        folder / "run3.mat",
        {
            "Cartposition": np.column_stack([p10.time, p10.position]),
            "u": _scope(p10.command, p10.time, block="labcartp/voltage out"),
        },
    )
    e = pi.reference - pi.position
    scipy.io.savemat(
        folder / "run4.mat",
        {
            "y": _scope(pi.position, pi.time, block="labcartpi/cart position"),
            "e": _scope(e, pi.time, block="labcartpi/error out"),
        },
    )
    return {"ramp": ramp, "p_error": p10, "pi": pi}


def test_a_whole_lab_of_raw_scopes_every_part_assigned(real_folder, tmp_path, capsys):
    """A whole lab's folder of raw .mat files as QUARC saved them (the real tap, P 50, its
    repeat and PD run; ramp, P 10 and a PI with only y and e from the generator): every
    recording goes to its part (what jaxcart lab --data uses), the repeat as a second run of
    Part (ii), each with its evidence, and jaxcart import says the same."""
    from tuning.commands.main import main
    from tuning.lab.inputs import find_inputs

    made = _student_scopes(real_folder)
    inputs = find_inputs(real_folder)
    assert {s: run.label for s, run in inputs.imported.items()} == {
        "tap": "part1.1.mat",
        "p_step": "2.1pos.mat + 2.1volt.mat",
        "ramp": "3.1pos.mat + 3.1volt.mat",
        "p_error": "run3.mat",
        "pi": "run4.mat",
        "pid": "5.1wksp_1.mat",
    }
    assert [Path(r.path).name for r in inputs.repeats["p_step"]] == ["p50_repeat.mat"]
    assert inputs.unused == [] and inputs.missing() == []
    from tuning.lab.classroom import used_files  # the class table flags no file as unused

    assert set(used_files(inputs)) >= {p.name for p in real_folder.glob("*.mat")}
    recs = inputs.recordings
    assert recs["ramp"].kind == "open_loop"
    np.testing.assert_array_equal(recs["ramp"].command, made["ramp"].command)
    assert (recs["p_error"].controller.kp, recs["p_error"].controller.ki) == (10.0, 0.0)
    assert (recs["pi"].controller.kp, recs["pi"].controller.ki) == (10.0, 15.0)
    np.testing.assert_allclose(recs["pi"].position, made["pi"].position, atol=1e-15)
    np.testing.assert_allclose(recs["pi"].reference, 0.2, atol=1e-15)  # r = y + e
    assert (recs["pid"].controller.kp, recs["pid"].controller.kd) == (55.0, 5.0)
    # Each assignment with its evidence: what the physics showed, strong.
    shown = "\n".join(inputs.summary_lines())
    for phrase in (
        "slows in proportion to its speed",
        "P with the handout's k = 50 V/m [strong]",
        "the voltage rises linearly with time, 0.1 V/s",
        "P with the handout's k = 10 V/m [strong]",
        "moves again toward e = 0",
        "a PD [strong]",
        "and a repeat: p50_repeat.mat",
    ):
        assert phrase in shown
    out = tmp_path / "imported"
    files = sorted(str(p) for p in real_folder.glob("*.mat"))
    assert main(["--no-cache", "import", *files, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("(strong evidence)") == 7
    assert "5.1wksp_1.mat:y is a copy of 5.1wksp_1.mat:Cartposition" in printed
    assert "not used: 5.1wksp_1.mat:ScopeData1 (name 'rod'" in printed
    assert len(list(out.glob("*.toml"))) == 7


def test_weak_evidence_is_a_question_in_the_lab(real_folder):
    from tuning.lab.inputs import find_inputs, write_used

    t, y, _ = _p50(2000)
    scipy.io.savemat(real_folder / "run7.mat", {"a": np.column_stack([t, 0.75 * y])})
    inputs = find_inputs(real_folder)
    reason = dict(inputs.unused)["run7.mat"]
    assert "evidence is weak" in reason
    assert "name its part in lab.toml, e.g. [recordings] " in reason and '= "run7.mat"' in reason
    assert "run7.mat" not in [Path(r.path).name for r in inputs.recordings.values()]
    report = real_folder.parent / "report"
    report.mkdir()
    write_used(inputs, report)
    offers = [x for x in (report / "lab.toml").read_text().splitlines() if "run7.mat" in x]
    assert offers and all(x.startswith("# ") and "weak evidence" in x for x in offers)
    assert all('= "../data/run7.mat"' in x for x in offers)
    (real_folder / "lab.toml").write_text('[recordings]\npid = "run7.mat"\n')
    named = find_inputs(real_folder)
    assert Path(named.recordings["pid"].path).name == "run7.mat"
    assert named.how["pid"] == "named in lab.toml"
    assert named.recordings["pid"].reference[0] == pytest.approx(0.3, abs=0.003)
    assert Path(named.recordings["tap"].path).name == "part1.1.mat"  # the rest still guessed


def test_import_command(real_folder, tmp_path, capsys):
    from tuning.commands.main import main

    out = tmp_path / "out"
    files = [str(real_folder / n) for n in ("2.1volt.mat", "2.1pos.mat", "part1.1.mat")]
    assert main(["--no-cache", "import", *files, "--out", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "Part (ii) P control k = 50 V/m, step 0.4 m [p_step] (strong evidence)" in shown
    assert "R^2 = 1.0000" in shown
    assert sorted(p.name for p in out.iterdir()) == ["2.1pos.toml", "part1.1.toml"]
    from_toml = read_experiment(out / "2.1pos.toml")
    direct = read_experiment(real_folder / "2.1pos.mat")
    np.testing.assert_array_equal(from_toml.position, direct.position)
    assert from_toml.controller == direct.controller
    assert main(["--no-cache", "import", files[1], "--out", str(out)]) == 2  # exists
    assert "exists" in capsys.readouterr().err
    # 2.1pos.mat alone brings its sibling 2.1volt.mat, as every other command reads it (the
    # import wrote "no voltage recorded").
    alone = tmp_path / "alone"
    assert main(["--no-cache", "import", files[1], "--out", str(alone)]) == 0
    assert "from 2.1pos.mat + 2.1volt.mat" in (alone / "2.1pos.toml").read_text()
    assert read_experiment(alone / "2.1pos.toml").command is not None
    capsys.readouterr()
    t, y, _ = _p50(1000)
    scipy.io.savemat(tmp_path / "x.mat", {"a": np.column_stack([t, 0.75 * y])})
    assert main(["--no-cache", "import", str(tmp_path / "x.mat"), "--out", str(out)]) == 2
    assert "the evidence is weak" in capsys.readouterr().err
    assert main(["--no-cache", "import", str(tmp_path / "x.mat"), "--as", "pid"]) == 0
    assert (tmp_path / "x.toml").is_file()
    # A run every command would refuse (positions saved in mm) is told what to convert, and
    # no experiment file is written (one that every later read refused, before).
    t, y, v = _p50(2000)
    scipy.io.savemat(tmp_path / "mm.mat", {"y": _scope(1000.0 * y, t), "v": _scope(v, t)})
    capsys.readouterr()
    assert main(["--no-cache", "import", str(tmp_path / "mm.mat"), "--as", "p_step"]) == 2
    err = capsys.readouterr().err
    assert "not written" in err and "recorded in mm? divide by 1000 for metres" in err
    assert not (tmp_path / "mm.toml").exists()


def test_slider_moves_recognised(tmp_path):
    """Part (v)'s slider: the designed PID sends the cart to several setpoints. With the
    reference recorded it reads as an experiment file; without, the reader says what to save;
    the lab's report has no part for it and says so."""
    import jax

    import jaxcart as jc
    from jaxcart.synthetic import make_recording
    from tuning.lab.data import PID_DESIGN, true_plant
    from tuning.lab.inputs import find_inputs

    levels = (0.2, -0.1, 0.15, -0.2)
    r = np.repeat(levels, 1200)
    with jax.enable_x64(True):
        exp = jc.Experiment(jax.numpy.asarray(r), kind="closed_loop", sample_time=0.001)
        rec = make_recording(true_plant(), jc.PID(**PID_DESIGN, v_limit=6.0), exp, seed=3)
    t = np.arange(r.size) * 0.001
    y, v = np.asarray(rec.position), np.asarray(rec.command)
    scipy.io.savemat(tmp_path / "s.mat", {"pos": _scope(y, t), "volt": _scope(v, t)})
    with pytest.raises(UserError, match="slider moves, but the reference .* map it as r"):
        read_experiment(tmp_path / "s.mat")
    scipy.io.savemat(tmp_path / "s.mat", {"pos": _scope(y, t), "volt": _scope(v, t), "ref": r})
    got = read_experiment(tmp_path / "s.mat", check=False)
    assert got.meta["notes"]["recognised_as"] == "slider"
    np.testing.assert_array_equal(got.reference, r)
    assert got.controller.kp == pytest.approx(PID_DESIGN["kp"], rel=1e-3)
    assert got.controller.kd == pytest.approx(PID_DESIGN["kd"], rel=1e-3)
    (tmp_path / "tap.toml").write_text(
        'kind = "tap"\nsample_time = 0.001\ndata = "tap.csv"\n'
    )  # the lab needs one recording it uses
    (tmp_path / "tap.csv").write_text("t,y\n" + "".join(f"{k / 1000},0.0\n" for k in range(50)))
    inputs = find_inputs(tmp_path)
    assert (
        dict(inputs.unused)["s.mat"]
        == "the designed PID, slider moves: no part of the report uses it"
    )


def test_v73_scope_with_several_inputs(tmp_path):
    """In a v7.3 file a struct array keeps each field as HDF5 object references into #refs#
    (MATLAB's layout): read as the same labelled signals as a v7 file's."""
    import h5py

    t, y, v = _p50(300)
    with h5py.File(tmp_path / "sa.mat", "w", userblock_size=512) as f:
        refs = f.create_group("#refs#")
        scope = f.create_group("ScopeData")
        scope.attrs["MATLAB_class"] = np.bytes_("struct")
        scope.create_dataset("time", data=t[None, :]).attrs["MATLAB_class"] = np.bytes_("double")
        signals = scope.create_group("signals")
        signals.attrs["MATLAB_class"] = np.bytes_("struct")
        values, labels = [], []
        for i, (x, label) in enumerate(((y, "cart position"), (v, "voltage out"))):
            ds = refs.create_dataset(f"v{i}", data=x[None, :])
            ds.attrs["MATLAB_class"] = np.bytes_("double")
            values.append(ds.ref)
            ds = refs.create_dataset(f"l{i}", data=np.array([[ord(c)] for c in label], np.uint16))
            ds.attrs["MATLAB_class"] = np.bytes_("char")
            labels.append(ds.ref)
        for name, items in (("values", values), ("label", labels)):
            signals.create_dataset(name, data=np.array(items, dtype=h5py.ref_dtype)[:, None])
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 ."
    with open(tmp_path / "sa.mat", "r+b") as f:
        f.write(header.ljust(116) + b"\0" * 8 + b"\x00\x02IM")
    found = matimport.read_signals(tmp_path / "sa.mat")
    assert [(s.source, s.role, s.names[1]) for s in found] == [
        ("sa.mat:ScopeData[1]", "y", "cart position"),
        ("sa.mat:ScopeData[2]", "v", "voltage out"),
    ]
    np.testing.assert_array_equal(found[0].values, y)
    np.testing.assert_array_equal(found[1].time, t)


def test_files_named_as_one_run_in_lab_toml_are_one_run_whatever_their_names(tmp_path, realdata):
    """The P 50 step's position and voltage files renamed so that their names do not pair
    (run2.mat, run3.mat): listed together in lab.toml they are that run (they were refused,
    "its files are not one run")."""
    from tuning.lab.inputs import find_inputs

    folder = tmp_path / "data"
    folder.mkdir()
    shutil.copyfile(Path(realdata) / "2.1pos.mat", folder / "run2.mat")
    shutil.copyfile(Path(realdata) / "2.1volt.mat", folder / "run3.mat")
    (folder / "lab.toml").write_text('[recordings]\np_step = ["run2.mat", "run3.mat"]\n')
    found = find_inputs(folder)
    rec = found.recordings["p_step"]
    assert rec.command is not None and float(np.max(np.abs(rec.command))) == pytest.approx(6.0)


# ---------------------------------------------------------------- saved differently (probe 9)


def test_numbered_time_vector_is_time_not_a_voltage(tmp_path):
    """MATLAB users number a session's runs: t1, time1, t_tap, tout1 are the time (they were
    read as a voltage: "values beyond 1"), and the run's time comes from them."""
    t, y, v = _p50(1500, ts=0.002)
    for names in (("t1", "y1", "u1"), ("time1", "pos1", "volt1"), ("t_p50", "y_p50", "u_p50")):
        path = tmp_path / f"{names[0]}.mat"
        scipy.io.savemat(path, dict(zip(names, (t, y, v), strict=True)), oned_as="column")
        roles = {s.source.split(":")[1]: s.role for s in matimport.read_signals(path)}
        assert roles == dict(zip(names, ("t", "y", "v"), strict=True))
        run = matimport.run_of(path)
        assert run.problem is None and not run.time_assumed and run.sample_time == 0.002
    assert matimport._role(("tap",), matfile.ScopeSignal(t, None, "", 1, 1), many=False)[0] != "t"


def test_two_runs_in_one_file_advice_maps_them(tmp_path):
    """Two runs saved in one .mat (y1, v1, y2, v2): choosing y1 leaves two voltages, and the
    advice is a [data] table (jaxcart import FILE.mat:v1 would take the voltage for the
    position); following it reads the run."""
    t, y, v = _p50(1500)
    t2, y2, v2 = _p50(1800)
    path = tmp_path / "p50.mat"
    scipy.io.savemat(
        path, {"y1": _scope(y, t), "v1": _scope(v, t), "y2": _scope(y2, t2), "v2": _scope(v2, t2)}
    )
    run = matimport.run_of(f"{path}:y1")
    assert "look like a voltage" in run.problem
    assert "jaxcart import" not in run.problem
    assert '[data] y = "p50.mat:y1", v = "p50.mat:v1"' in run.problem
    (tmp_path / "run1.toml").write_text(
        'kind = "closed_loop"\n[data]\ny = "p50.mat:y1"\nv = "p50.mat:v1"\n'
        '[controller]\nkp = 50.0\nv_limit = 6.0\n[reference]\nkind = "step"\namplitude = 0.4\n'
    )
    assert read_experiment(tmp_path / "run1.toml").n_samples == 1500


def test_lab_finds_upper_case_mat_and_says_why_no_run_is_used(real_folder, tmp_path):
    """A Windows copy's PART1.1.MAT is the tap (it was left out, unsaid); a folder whose only
    .mat holds two runs says why, not 'no experiment files found'."""
    from tuning.lab.inputs import find_inputs

    (real_folder / "part1.1.mat").rename(real_folder / "PART1.1.MAT")
    inputs = find_inputs(real_folder)
    assert Path(inputs.recordings["tap"].path).name == "PART1.1.MAT"
    lone = tmp_path / "lone"
    lone.mkdir()
    t, y, v = _p50(1500)
    tap = scipy.io.loadmat(real_folder / "PART1.1.MAT")["Cartposition"]
    scipy.io.savemat(lone / "lab1.mat", {"Cartposition": tap, "y": _scope(y, t), "v": _scope(v, t)})
    with pytest.raises(UserError, match="no recording can be used: lab1.mat: 2 different signals"):
        find_inputs(lone)


# ---------------------------------------------------------------- CSV files of named columns


def _csv(path, header, *columns):
    np.savetxt(path, np.column_stack(columns), delimiter=",", header=header, comments="")


def test_a_csv_of_named_columns_is_a_raw_recording(tmp_path, capsys):
    """Another simulator's CSV ("time,position,voltage", no experiment file) is recognised as
    a .mat run is, read as its experiment, and imported to a TOML that maps its columns."""
    from tuning.commands.main import main

    t, y, v = _p50(2000)
    _csv(tmp_path / "other_sim.csv", "time,position,voltage", t, y, v)
    got = read_experiment(tmp_path / "other_sim.csv")
    assert got.meta["notes"]["recognised_as"] == "p_step"
    assert got.controller.kp == pytest.approx(50.0, rel=1e-3)
    np.testing.assert_array_equal(got.position, y)
    assert main(["--no-cache", "import", str(tmp_path / "other_sim.csv")]) == 0
    toml = (tmp_path / "other_sim.toml").read_text()
    assert 'y = "other_sim.csv:position"' in toml and 't = "other_sim.csv:time"' in toml
    np.testing.assert_array_equal(read_experiment(tmp_path / "other_sim.toml").position, y)
    # The data of an experiment file is read through it, not guessed.
    with pytest.raises(UserError, match=r"other_sim.csv is the data of .*other_sim.toml"):
        read_experiment(tmp_path / "other_sim.csv")
    # A column chosen as the position, as a muxed scope's signal is.
    _csv(tmp_path / "two.csv", "t,a,b,voltage", t, y, 0.5 * y, v)
    assert matimport.run_of(f"{tmp_path / 'two.csv'}:a").signals["y"].source == "two.csv:a"
    with pytest.raises(UserError, match=r"no column 'c' \(columns: t, a, b, voltage\)"):
        matimport.run_of(f"{tmp_path / 'two.csv'}:c")
    # No column named time: the first, a steady clock; a speed is no voltage (it was taken for
    # a second one).
    _csv(tmp_path / "sim2.csv", "col1,x,x_dot,u", t, y, np.gradient(y, t), v)
    run = matimport.run_of(tmp_path / "sim2.csv")
    assert run.signals["t"].why == "the first column, a steady clock"
    assert [s.source for s in run.ignored] == ["sim2.csv:x_dot"]
    assert run.guess.experiment == "p_step" and run.sample_time == pytest.approx(0.001)


def test_a_raw_file_in_other_units_by_its_names_is_read_in_si(tmp_path):
    """Columns and variables named with their unit ("t [ms]", "Cart position [mm]", "y_mm",
    "time_ms")
    are in s, m and V once read: by the import (the sample time, recognition) and through the
    experiment file that maps them; a unit of another quantity in a mapped name is one line."""
    from tuning.commands.main import main

    t, y, v = _p50(2000)
    _csv(tmp_path / "ms_mm.csv", "t [ms],Cart position [mm],voltage", 1e3 * t, 1e3 * y, v)
    run = matimport.run_of(tmp_path / "ms_mm.csv")
    assert run.sample_time == pytest.approx(0.001, rel=1e-12)
    assert run.guess.experiment == "p_step"
    assert main(["--no-cache", "import", str(tmp_path / "ms_mm.csv")]) == 0
    rec = read_experiment(tmp_path / "ms_mm.toml")
    np.testing.assert_allclose(rec.position, y, rtol=1e-12, atol=1e-15)
    assert rec.controller.kp == pytest.approx(50.0, rel=1e-3)
    scipy.io.savemat(tmp_path / "mm.mat", {"y_mm": 1e3 * y, "v": v, "t": t})
    rec = read_experiment(tmp_path / "mm.mat")
    np.testing.assert_allclose(rec.position, y, rtol=1e-12, atol=1e-15)
    # A whole word before the unit, as a logger writes it (was 1 s a sample, P 50 unstable);
    # a suffix after a word of another quantity is no unit.
    from hw.expfile import named_unit

    assert [named_unit(n) for n in ("pos_s", "v_sim_s", "volt_m")] == [None, None, None]
    _csv(tmp_path / "log.csv", "time_ms,position_mm,voltage_V", 1e3 * t, 1e3 * y, v)
    rec = read_experiment(tmp_path / "log.csv")
    assert rec.sample_time == pytest.approx(0.001, rel=1e-12) and not rec.warnings
    np.testing.assert_allclose(rec.position, y, rtol=1e-12, atol=1e-15)
    (tmp_path / "bad.toml").write_text(
        'kind = "closed_loop"\nsample_time = 0.001\n[data]\ny = "ms_mm.csv:t [ms]"\n'
        "[controller]\nkp = 50.0\n"
    )
    with pytest.raises(UserError, match=r"its name says ms, but y is the position \[m\]"):
        read_experiment(tmp_path / "bad.toml")


def test_a_table_saved_otherwise_reads_as_its_csv(tmp_path):
    """The same run saved as a tab-separated .tsv (a logger's export), with semicolons and
    decimal commas (a European Excel's CSV), with a byte-order mark and CRLF line ends, and
    in ms and mm with a units line under the names: each reads as the comma-separated CSV
    does, through the import's experiment file too, and a lab folder takes the .tsv (it was
    refused: "not a .mat or .csv file")."""
    from tuning.commands.main import main
    from tuning.lab.inputs import find_inputs

    t, y, v = _p50(2000)
    rows = list(zip(t, y, v, strict=True))
    (tmp_path / "log.tsv").write_text(
        "time\tposition\tvoltage\n" + "".join(f"{a:.17g}\t{b:.17g}\t{c:.17g}\n" for a, b, c in rows)
    )
    (tmp_path / "eu.csv").write_text(
        "time;position;voltage\n"
        + "".join(f"{a:.4f};{b:.7f};{c:.5f}\n".replace(".", ",") for a, b, c in rows)
    )
    with open(tmp_path / "bom.csv", "w", encoding="utf-8-sig", newline="\r\n") as f:
        body = "".join(f"{a:.17g},{b:.17g},{c:.17g}\n" for a, b, c in rows)
        f.write("time,position,voltage\n" + body)
    (tmp_path / "units.csv").write_text(
        "time,position,voltage\nms,mm,V\n"
        + "".join(f"{1e3 * a:.17g},{1e3 * b:.17g},{c:.17g}\n" for a, b, c in rows)
    )
    for name in ("log.tsv", "eu.csv", "bom.csv", "units.csv"):
        got = read_experiment(tmp_path / name)
        np.testing.assert_allclose(got.position, y, rtol=0, atol=1e-7, err_msg=name)
        assert got.meta["notes"]["recognised_as"] == "p_step", name
    out = tmp_path / "o"
    assert main(["--no-cache", "import", str(tmp_path / "log.tsv"), "--out", str(out)]) == 0
    rec = read_experiment(tmp_path / "o" / "log.toml")
    np.testing.assert_array_equal(rec.position, y)
    assert rec.controller.kp == pytest.approx(50.0, rel=1e-3)
    lab = tmp_path / "lab"
    lab.mkdir()
    shutil.copy(tmp_path / "log.tsv", lab)
    inputs = find_inputs(lab)
    np.testing.assert_array_equal(inputs.recordings["p_step"].position, y)
    # pandas' DataFrame.to_csv: an unnamed index first. It is no signal: it was a second
    # voltage (a question), and without a time column it was the time, 1 s a sample.
    for name, head, cols in (("pandas.csv", ",time,position,voltage", (t, y, v)),
                             ("pandas2.csv", "Unnamed: 0,position,voltage", (y, v))):  # fmt: skip
        _csv(tmp_path / name, head, np.arange(t.size), *cols)
        run = matimport.run_of(tmp_path / name)
        assert run.problem is None and run.sample_time == pytest.approx(0.001), name
        assert [s.why for s in run.ignored] == ["a row index (0, 1, 2, ...), not a signal"]
        got = read_experiment(tmp_path / name)
        np.testing.assert_array_equal(got.position, y)
        assert got.controller.kp == pytest.approx(50.0, rel=1e-3)


def test_a_scope_started_before_the_step_is_the_step(tmp_path):
    """A P 50 step recorded from 0.5 s before it (the cart at rest, the command at 0 V): the
    controller is identified from the step on and the run is Part (ii)'s, with strong
    evidence; the experiment file it writes reads with the step where the data put it. (It
    was "weak evidence, a tap or a P step", the controller unknown.)"""
    t, y, v = _p50(2000)
    rest = 500
    t = np.arange(2000 + rest) * 0.001
    y, v = np.concatenate([np.zeros(rest), y]), np.concatenate([np.zeros(rest), v])
    _csv(tmp_path / "late.csv", "t,y,v", t, y, v)
    run = matimport.run_of(tmp_path / "late.csv")
    assert run.guess.experiment == "p_step" and run.guess.confident, run.guess.evidence
    assert any("from its step at t = 0.500 s" in e.text for e in run.guess.evidence)
    assert run.guess.step == pytest.approx(0.4, abs=1e-3)
    rec = read_experiment(matimport.write_imported(run, tmp_path / "late.toml"))
    assert rec.controller.kp == pytest.approx(50.0, rel=1e-3)
    r = np.asarray(rec.reference)
    assert np.all(r[:rest] == 0.0) and np.all(r[rest:] == pytest.approx(0.4, abs=1e-3))


def test_the_lab_takes_a_folder_of_csv_files(tmp_path):
    """A data folder of raw CSV files: each run recognised for its part; a CSV that is no
    recording is listed unused, and the lab goes on."""
    from tuning.lab.inputs import find_inputs

    t, y, v = _p50(2000)
    _csv(tmp_path / "p50_run.csv", "time,cart position,voltage", t, y, v)
    (tmp_path / "notes.csv").write_text("student,grade\nalice,A\n")
    # What jaxcart simulate wrote beside the data and below it is no run of the cart (it was
    # taken as a second run of its part, and fitted with the recordings).
    from tuning.commands.main import main

    for out in ("p50-sim.csv", "jaxcart-out/p50-sim.csv"):
        sim = ["simulate", str(tmp_path / "p50_run.csv"), "--out", str(tmp_path / out)]
        assert main(["--no-cache", *sim]) == 0
    inputs = find_inputs(tmp_path)
    assert inputs.how["p_step"] == "recognised, strong evidence"
    np.testing.assert_array_equal(inputs.recordings["p_step"].position, y)
    unused = dict(inputs.unused)
    assert "not a recording" in unused["notes.csv"]
    for name in ("p50-sim.toml", "jaxcart-out/p50-sim.toml"):
        assert unused[name].startswith("a simulation (jaxcart simulate (exact simulator) of")
    assert not inputs.repeats


def test_a_scopes_last_samples_are_imported_as_recorded_and_said_so(builtin, tmp_path):
    """A scope that kept only the PI run's last 5 s (the students' Part (iv) error was saved
    from t = 15 s): the file gets the step its first error says, the description says that
    this is not the handout's step, and reading it warns that its clock starts late, when the
    PI's integral had built up (which the simulations start at 0)."""
    rec = builtin["pi"]
    tail = rec.time >= 5.0
    e = (rec.reference - rec.position)[tail]
    scipy.io.savemat(tmp_path / "4.1err.mat", {"Error": np.column_stack([rec.time[tail], e])})
    (run,) = matimport.scan([tmp_path / "4.1err.mat"])
    assert run.guess.experiment == "pi"
    toml = matimport.write_imported(run, tmp_path / "4.1err.toml")
    got = read_experiment(toml)
    step = float(got.reference[0])
    assert step == pytest.approx(e[0], rel=0.01)  # the first error: the cart taken at 0
    assert f"its step {step:.4g} m, not the handout's" in toml.read_text()
    (late,) = [w for w in got.warnings if "integral" in w]
    assert "the time starts at t = 5 s" in late and "ki = 15 V/(m s)" in late
    # A tail under a millimetre (the students' error_section4.mat: 0.96 mm from t = 15 s): no
    # step to read, said with the error it starts at (it said "starts at zero"), and a question.
    flat = np.full(2246, 0.956e-3)
    t15 = 15.0 + np.arange(flat.size) * 0.001
    scipy.io.savemat(tmp_path / "es4.mat", {"Error": np.column_stack([t15, flat])})
    (run,) = matimport.scan([tmp_path / "es4.mat"])
    assert not run.guess.confident
    assert any("starts at 0.956 mm, under 1 mm: no step" in e.text for e in run.guess.evidence)
