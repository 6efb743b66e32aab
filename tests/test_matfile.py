"""Runs as MATLAB .mat files (jaxcart.matfile): every Simulink layout read back by jaxcart's
reader exactly, the field layout MATLAB expects (scipy.io.loadmat as MATLAB structs), a
recording written back in the layout it came in, and ``jaxcart simulate --out run.mat``."""

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest
import scipy.io

import jaxcart as jc
from jaxcart import matfile
from jaxcart.errors import UserError
from jaxcart.files import read_experiment
from tuning.commands import simulate as simulate_command
from tuning.commands.main import build_parser, main

PID = jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)


@pytest.fixture(scope="module")
def run():
    # 801 samples, the shape of test_interop and of the command below: one compile for all.
    return jax.jit(jc.simulate)(jc.handout_plant(), PID, jc.step(0.5, horizon=0.8))


@pytest.mark.parametrize("layout", matfile.LAYOUTS)
def test_each_layout_reads_back_exactly(layout, run, tmp_path):
    toml, mat = matfile.write_mat_experiment(
        tmp_path / "run.mat", run, controller=PID, layout=layout, plant_overrides={"f_c": 0.3}
    )
    rec = read_experiment(toml)
    assert rec.kind == "closed_loop" and rec.controller == PID
    assert rec.plant_overrides == {"f_c": 0.3} and rec.sample_time == 0.001
    for got, want in (
        (rec.time, run.time),
        (rec.position, run.position),
        (rec.command, run.command),
        (rec.reference, run.reference),
    ):
        np.testing.assert_array_equal(got, np.asarray(want))  # float64 in the file: exact
    assert {s.layout for s in matfile.source_layout(rec).values()} == {layout}
    with pytest.raises(UserError, match="exists"):
        matfile.write_mat_experiment(tmp_path / "run.mat", run, controller=PID, layout=layout)


def test_field_layout_matlab_expects(run, tmp_path):
    """Loaded as MATLAB structs (loadmat's defaults, as MATLAB's load sees them)."""
    n = run.time.shape[0]
    _, mat = matfile.write_mat_experiment(tmp_path / "a.mat", run, controller=PID)
    data = scipy.io.loadmat(mat)
    assert sorted(k for k in data if not k.startswith("__")) == ["e", "r", "v", "y"]
    y = data["y"][0, 0]
    assert y.dtype.names == ("time", "signals", "blockName")
    assert y["time"].shape == (n, 1) and y["time"].dtype == np.float64
    signals = y["signals"][0, 0]
    assert signals.dtype.names == ("values", "dimensions", "label")
    assert signals["values"].shape == (n, 1) and signals["dimensions"].item() == 1
    assert signals["label"].item() == "y" and y["blockName"].item() == "jaxcart/y"
    _, mat = matfile.write_mat_experiment(tmp_path / "b.mat", run, layout="array")
    assert scipy.io.loadmat(mat)["v"].shape == (n, 2)  # [t, value]
    _, mat = matfile.write_mat_experiment(tmp_path / "c.mat", run, layout="structure")
    assert scipy.io.loadmat(mat)["y"][0, 0]["time"].size == 0


def _lab_scope(tmp_path, n=801, ts=0.001):
    """A Part (ii) recording as the lab's Simulink scopes save it (2.1pos.mat/2.1volt.mat:
    "Structure" with an empty time, a block name, variables y and v in two files)."""
    t = np.arange(n) * ts
    y = 0.4 * (1 - np.exp(-t / 0.3)) ** 2  # a cart's speeds and accelerations
    for file, name, values, block in (
        ("pos.mat", "y", y, "labcartsat/cart position"),
        ("volt.mat", "v", np.clip(50.0 * (0.4 - y), -6, 6), "labcartsat/voltage out"),
    ):
        signals = {"values": values[:, None], "dimensions": np.uint8(1), "label": ""}
        scope = {"time": np.zeros((0, 0)), "signals": signals, "blockName": block}
        scipy.io.savemat(tmp_path / file, {name: scope})
    (tmp_path / "p.toml").write_text(
        'kind = "closed_loop"\nsample_time = 0.001\n[data]\ny = "pos.mat:y"\n'
        'v = "volt.mat:v"\n[controller]\nkp = 50.0\nv_limit = 6.0\n'
        '[reference]\nkind = "step"\namplitude = 0.4\n'
    )
    return tmp_path / "p.toml"


def test_simulate_writes_back_the_layout_it_came_in(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    source = _lab_scope(tmp_path)
    args = build_parser().parse_args(["simulate", str(source)])
    default = simulate_command._outputs(args, read_experiment(source))[0]
    assert default == Path("jaxcart-out/p-sim.mat")  # .mat in: .mat out, without --out
    assert main(["simulate", str(source), "--out", "p-sim.mat"]) == 0
    assert "p-sim.mat" in capsys.readouterr().out
    out = read_experiment(tmp_path / "p-sim.toml")
    layout = matfile.source_layout(out)
    assert layout["y"] == matfile.SignalLayout("structure", "y", "labcartsat/cart position", "")
    assert layout["v"].block_name == "labcartsat/voltage out"
    assert layout["r"].layout == "structure" and out.controller.kp == 50.0
    exp = read_experiment(source).experiment
    again = jc.simulate(out.plant(), out.controller, exp, solver=jc.Exact())  # the default
    np.testing.assert_allclose(out.position, np.asarray(again.position), rtol=0, atol=1e-12)

    assert main(["simulate", str(source), "--out", "x.mat", "--mat-layout", "array"]) == 0
    assert matfile.source_layout(read_experiment("x.toml"))["y"].layout == "array"
    assert main(["simulate", str(source), "--out", "x.xlsx"]) == 2
    assert ".csv or .mat" in capsys.readouterr().err
    assert (
        simulate_command.MAT_LAYOUTS == matfile.LAYOUTS
    )  # the parser's copy (it must not import jaxcart)


def _count_loads(monkeypatch):
    """{file name: times scipy.io.loadmat read it}, counting every load from now on."""
    counts: dict = {}
    real = scipy.io.loadmat

    def counting(path, *args, **kwargs):
        counts[Path(path).name] = counts.get(Path(path).name, 0) + 1
        return real(path, *args, **kwargs)

    monkeypatch.setattr(scipy.io, "loadmat", counting)
    return counts


def test_each_mat_file_is_read_once(tmp_path, monkeypatch, capsys):
    """Reading a recording loads each .mat file once, and the layout it came in is noted then:
    source_layout, write_mat_recording and `jaxcart simulate --out x.mat` read none again,
    and give what loading the files afresh gives."""
    source = _lab_scope(tmp_path)
    counts = _count_loads(monkeypatch)
    rec = read_experiment(source)
    assert counts == {"pos.mat": 1, "volt.mat": 1}
    layout = matfile.source_layout(rec)
    assert layout["y"] == matfile.SignalLayout("structure", "y", "labcartsat/cart position", "")
    assert layout["v"].block_name == "labcartsat/voltage out"
    # The same as loading the files afresh (a recording without the noted layouts).
    afresh = matfile.source_layout(dataclasses.replace(rec, mat_layout=None))
    assert afresh == layout and counts == {"pos.mat": 2, "volt.mat": 2}
    counts.clear()
    matfile.write_mat_recording(tmp_path / "copy.mat", rec)
    assert counts == {}
    copied = matfile.source_layout(read_experiment(tmp_path / "copy.toml"))
    assert {k: copied[k] for k in layout} == layout  # and r, e (written) in the same layout
    counts.clear()
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", str(source), "--out", "sim.mat"]) == 0
    assert counts == {"pos.mat": 1, "volt.mat": 1}
    capsys.readouterr()
    # CSV data: no layout, nothing loaded.
    csv = read_experiment(Path(jc.__file__).parent / "data" / "tap.toml")
    assert csv.mat_layout == {} and matfile.source_layout(csv) == {}


def test_real_recording_converts_to_mat(realdata, tmp_path):
    """A recording (here the real P50 run) as .mat in the layout it came in, read back equal."""
    rec = read_experiment(f"{realdata}/p50.toml")
    toml, _ = matfile.write_mat_experiment(
        tmp_path / "p50.mat",
        rec.as_response(),
        controller=rec.controller,
        source=matfile.source_layout(rec),
    )
    back = read_experiment(toml)
    np.testing.assert_array_equal(back.position, rec.position)
    np.testing.assert_array_equal(back.command, rec.command)
    assert matfile.source_layout(back)["y"].block_name == "labcartsat/cart position"


def test_recording_with_provenance_converts_to_mat(tmp_path):
    """A CSV recording (as the hardware loop writes it, with provenance tables and a push)
    written as .mat keeps every signal, the start velocity and the tables."""
    t = np.arange(200) * 0.001
    y = 0.1 + 0.08 * (1 - np.exp(-t / 0.2))
    np.savetxt(
        tmp_path / "tap.csv",
        np.column_stack([t, y]),
        delimiter=",",
        header="t,y",
        comments="",
        fmt="%.17g",
    )
    (tmp_path / "tap.toml").write_text(
        'description = "a push"\nkind = "tap"\nsample_time = 0.001\n'
        'initial_velocity = 0.4\ndata = "tap.csv"\n[tap]\nmotor_connected = true\n'
        '[device]\nname = "sim"\nrate = 1000\n[run]\nstopped = false\n'
    )
    rec = read_experiment(tmp_path / "tap.toml")
    toml, _ = matfile.write_mat_recording(tmp_path / "push.mat", rec)
    back = read_experiment(toml)
    np.testing.assert_array_equal(back.position, y)
    np.testing.assert_array_equal(back.time, t)
    assert back.experiment.yd0 == 0.4 and back.meta["tap"]["motor_connected"] is True
    assert (
        back.meta["device"] == {"name": "sim", "rate": 1000}
        and back.meta["description"] == "a push"
    )
    assert scipy.io.loadmat(tmp_path / "push.mat")["y"][0, 0]["time"].shape == (200, 1)


def test_result_report_as_a_matlab_struct(tmp_path):
    """A fit report (JSON-like) as one struct: field names MATLAB accepts, None as NaN."""
    report = {
        "params": {"B_eq": {"value": 4.1, "stderr": 0.02}, "f_c": {"value": 0.3, "stderr": None}},
        "correlation": {"B_eq,f_c": -0.4},
        "recordings": [{"name": "p50", "rms_after": 1e-3}, {"name": "tap", "rms_after": None}],
        "values": [4.1, 0.3],
        "2nd": True,
    }
    path = matfile.write_mat_report(tmp_path / "fit.mat", report, name="fit")
    fit = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)["fit"]
    assert fit._fieldnames == ["params", "correlation", "recordings", "values", "x2nd"]
    assert fit.params.B_eq.stderr == 0.02 and np.isnan(fit.params.f_c.stderr)
    assert fit.correlation.B_eq_f_c == -0.4 and fit.recordings[1].name == "tap"
    np.testing.assert_array_equal(fit.values, [4.1, 0.3])
    with pytest.raises(UserError, match="exists"):
        matfile.write_mat_report(path, report)
