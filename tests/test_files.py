"""Experiment files: exact round trips, the lab's real recordings (checked against the control law
and the encoder resolution), the Simulink .mat layouts, and one-line errors for bad input."""

import dataclasses
import re

import jax
import numpy as np
import pytest
import scipy.io

import jaxcart as jc
from jaxcart.errors import UserError
from jaxcart.files import read_experiment, write_experiment
from jaxcart.plantspec import build_plant

# One jitted simulator for the file, shared with the command's (same function, same cache).
simulate = jax.jit(jc.simulate)

#: A written file read back: the CSV holds 17 significant digits, so values agree to rounding.
ROUND_TRIP_TOL = 1e-12
#: Encoder resolution seen in the lab's recordings (README of realdata) [m/count].
COUNT = 2.2735e-5


# ---------------------------------------------------------------- round trips


def _assert_same_run(rec, res):
    for name, ours in (("time", rec.time), ("position", rec.position)):
        np.testing.assert_allclose(
            ours, np.asarray(getattr(res, name)), rtol=0, atol=ROUND_TRIP_TOL, err_msg=name
        )


def test_closed_loop_round_trip_keeps_every_setting(tmp_path):
    pid = jc.PID(
        kp=35.0,
        ki=4.5,
        kd=3.25,
        tau=0.005,
        v_limit=5.5,
        kb=2.5,
        sample_time=0.002,
        derivative_on="measurement",
        anti_windup="back_calculation",
    )
    overrides = {"M": 1.1, "B_eq": 4.8, "f_c": 0.3, "v_sat": 5.0, "gamma_scale": 0.97}
    plant = build_plant(overrides)
    res = simulate(plant, pid, jc.step(0.3, horizon=0.4, sample_time=0.002, y0=0.01))
    path = write_experiment(
        tmp_path / "run.toml",
        res,
        controller=pid,
        plant_overrides=overrides,
        description='a "quoted"\nrun \\ 1',
    )
    assert path == tmp_path / "run.toml" and (tmp_path / "run.csv").is_file()

    rec = read_experiment(path)
    assert rec.kind == "closed_loop" and rec.sample_time == 0.002 and rec.n_samples == 201
    assert rec.controller == pid
    assert rec.plant_overrides == overrides
    assert rec.meta["description"] == 'a "quoted"\nrun \\ 1'
    _assert_same_run(rec, res)
    for ours, theirs in ((rec.command, res.command), (rec.reference, res.reference)):
        np.testing.assert_allclose(ours, np.asarray(theirs), rtol=0, atol=ROUND_TRIP_TOL)
    # The experiment read back simulates to the same run (same inputs, same controller).
    again = simulate(rec.plant(), rec.controller, rec.experiment)
    np.testing.assert_allclose(
        np.asarray(again.position), np.asarray(res.position), rtol=0, atol=ROUND_TRIP_TOL
    )


def test_open_loop_and_tap_round_trips(tmp_path):
    res = simulate(jc.handout_plant(), jc.PID(), jc.voltage_step(2.0, horizon=0.3))
    rec = read_experiment(write_experiment(tmp_path / "ol.csv", res))
    assert rec.kind == "open_loop" and rec.controller is None and rec.reference is None
    np.testing.assert_allclose(rec.command, 2.0, rtol=0, atol=0)
    np.testing.assert_allclose(np.asarray(rec.experiment.signal), 2.0, rtol=0, atol=0)
    _assert_same_run(rec, res)

    res = simulate(jc.tap_plant(), jc.PID(), jc.tap(0.8, horizon=0.5, y0=0.05))
    rec = read_experiment(write_experiment(tmp_path / "tap", res))
    assert rec.kind == "tap" and rec.command is None
    assert rec.experiment.yd0 == 0.8 and rec.experiment.y0 == 0.05
    assert rec.plant().motor_connected is False
    again = simulate(rec.plant(), jc.PID(), rec.experiment)
    np.testing.assert_allclose(
        np.asarray(again.position), np.asarray(res.position), rtol=0, atol=ROUND_TRIP_TOL
    )


def test_write_refuses_to_overwrite_without_force(tmp_path):
    res = simulate(jc.handout_plant(), jc.PID(kp=20.0), jc.step(0.1, horizon=0.05))
    write_experiment(tmp_path / "a.toml", res, controller=jc.PID(kp=20.0))
    # No software limit is written as an omitted v_limit and read back as inf.
    assert "v_limit" not in (tmp_path / "a.toml").read_text()
    assert read_experiment(tmp_path / "a.toml").controller == jc.PID(kp=20.0)
    (tmp_path / "b.csv").write_text("mine\n")
    for name, existing in (("a.toml", "a.toml"), ("b.toml", "b.csv")):
        with pytest.raises(UserError, match=rf"{existing} exists.*--force"):
            write_experiment(tmp_path / name, res)
    assert (tmp_path / "b.csv").read_text() == "mine\n"
    write_experiment(tmp_path / "b.toml", res, force=True)
    assert (tmp_path / "b.csv").read_text().startswith("t,y,v,r,e\n")


# ---------------------------------------------------------------- the real recordings


def test_real_tap_recording(realdata):
    rec = read_experiment(f"{realdata}/tap.toml")
    assert rec.kind == "tap" and rec.sample_time == 0.001 and rec.n_samples == 6030
    assert rec.time[0] == 0.0 and rec.time[-1] == pytest.approx(6.029, abs=1e-12)
    np.testing.assert_allclose(np.diff(rec.time), 0.001, rtol=1e-9)
    # Metres: every sample is a whole number of encoder counts (to 0.05 count over 22000 counts).
    counts = rec.position / COUNT
    assert np.abs(counts - np.round(counts)).max() < 0.05
    # README: at rest (one spurious count near 2.09 s) until the tap at ~3.16 s, at rest by 4.4 s.
    before, after = rec.position[rec.time < 3.15], rec.position[rec.time > 4.42]
    assert np.abs(before).max() <= 1.5 * COUNT and np.ptp(after) == 0.0
    assert after[0] == pytest.approx(0.5017, abs=1e-4)
    assert rec.command is None and rec.reference is None and rec.controller is None
    exp = rec.experiment
    assert exp.kind == "tap" and exp.n_samples == 6030 and exp.y0 == 0.0
    assert not np.any(np.asarray(exp.signal))
    assert rec.plant().motor_connected is False and float(rec.plant().B_emf) == 0.0


def test_real_p50_recording(realdata):
    rec = read_experiment(f"{realdata}/p50.toml")
    assert rec.kind == "closed_loop" and rec.n_samples == 2705 and rec.command.shape == (2705,)
    assert rec.time[0] == 0.0 and rec.time[-1] == pytest.approx(2.704, abs=1e-12)
    assert rec.controller == jc.PID(kp=50.0, v_limit=6.0)
    np.testing.assert_array_equal(rec.reference, 0.4)
    np.testing.assert_array_equal(np.asarray(rec.experiment.signal), 0.4)
    # Independent check of units and alignment: the recorded volts are the P law (k = 50 V/m,
    # 6 V limit) of the recorded metres, sample by sample, to rounding.
    law = np.clip(50.0 * (0.4 - rec.position), -6.0, 6.0)
    np.testing.assert_allclose(rec.command, law, rtol=0, atol=1e-12)
    assert 0.4 - rec.position[-1] == pytest.approx(3.05e-3, abs=0.1e-3)  # "3 mm short"
    counts = rec.position / COUNT
    assert np.abs(counts - np.round(counts)).max() < 0.05


# ---------------------------------------------------------------- data layouts


def _toml(tmp_path, text, name="exp.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_kinds_read_with_another_case_spaces_or_hyphens(tmp_path):
    """ "Closed loop", "closed-loop" and [reference] kind = "Step" are the format's closed_loop
    and step (the step's amplitude is then the reference, as with its own spelling); a kind
    that is none of them still stops with the allowed ones."""
    t = np.arange(200) * 0.001
    (tmp_path / "run.csv").write_text("t,y\n" + "".join(f"{a:.3f},0\n" for a in t))
    body = (
        'data = "run.csv"\n[controller]\nkp = 10.0\n[reference]\nkind = "{ref}"\namplitude = 0.1\n'
    )
    for kind, ref in (("Closed loop", "Step"), ("closed-loop", " STEP "), ("closed_loop", "step")):
        rec = read_experiment(_toml(tmp_path, f'kind = "{kind}"\n' + body.format(ref=ref)))
        assert rec.kind == "closed_loop" and np.all(rec.reference == 0.1)
    with pytest.raises(UserError, match="kind = 'closed loops': use one of 'tap'"):
        read_experiment(_toml(tmp_path, 'kind = "closed loops"\n' + body.format(ref="step")))


def test_time_stamps_read_with_jitter_are_a_uniform_clock(tmp_path):
    """Stamps that scatter about t_0 + k Ts by up to a quarter of a sample (a logger's clock)
    read as uniform, with a warning that says by how much; a clock whose steps drift (a wrong
    sample_time) still stops with the line where it leaves the step."""
    rng = np.random.default_rng(1)
    k = np.arange(500)
    y = 0.1 * (1 - np.exp(-k * 0.001 / 0.05))
    tap = 'kind = "tap"\nsample_time = 0.001\ndata = "run.csv"\n'
    for t in (5.0 + k * 0.001 + rng.uniform(-2e-4, 2e-4, k.size), k * 0.00102):
        body = "".join(f"{a:.9f},{b:.9f}\n" for a, b in zip(t, y, strict=True))
        (tmp_path / "run.csv").write_text("t,y\n" + body)
        if t[0] == 0.0:
            with pytest.raises(UserError, match=r"steps by 0.00102 s at line 3, more than 1 %"):
                read_experiment(_toml(tmp_path, tap))
            continue
        rec = read_experiment(_toml(tmp_path, tap))
        np.testing.assert_array_equal(rec.time, np.round(t, 9))
        assert rec.sample_time == 0.001
        said = [re.search(r"scatter by up to (\d+) us", w) for w in rec.warnings]
        assert [150 < float(m[1]) < 260 for m in said if m] == [True], rec.warnings


def test_mat_layouts_and_mapped_csv_columns(tmp_path):
    n, ts = 50, 0.002
    t = np.arange(n) * ts
    y = 0.3 * (1 - np.exp(-t / 0.02))
    scope = {"time": t[:, None], "signals": {"values": y[:, None], "dimensions": 1}}
    scipy.io.savemat(
        tmp_path / "s.mat", {"ys": scope, "vcol": (2 * y)[:, None], "yrow": np.vstack([t, y])}
    )
    np.savetxt(
        tmp_path / "d.csv",
        np.column_stack([t, y, -y]),
        delimiter=",",
        header="time,pos,volt",
        comments="",
        fmt="%.17g",
    )
    path = _toml(tmp_path, 'kind = "open_loop"\n[data]\ny = "s.mat:ys"\nv = "s.mat:vcol"\n')
    rec = read_experiment(path)  # time from the structure; sample_time inferred from it
    assert rec.sample_time == ts
    np.testing.assert_array_equal(rec.time, t)
    np.testing.assert_array_equal(rec.position, y)
    np.testing.assert_array_equal(np.asarray(rec.experiment.signal), 2 * y)  # input = column v
    rec = read_experiment(_toml(tmp_path, 'kind = "tap"\n[data]\ny = "s.mat:yrow"\n', "b.toml"))
    np.testing.assert_array_equal(rec.time, t)  # MATLAB's 2 x N [t; value] form
    text = 'kind = "open_loop"\nsample_time = 0.002\n[data]\nt = "d.csv:time"\ny = "d.csv:pos"\n'
    rec = read_experiment(_toml(tmp_path, text + 'v = "d.csv:volt"\n', "c.toml"))
    np.testing.assert_array_equal(rec.command, -y)


def test_reference_and_input_kinds(tmp_path):
    t = np.arange(11) * 0.01
    np.savetxt(
        tmp_path / "d.csv",
        np.column_stack([t, 0.02 + 0 * t]),
        delimiter=",",
        header="t,y",
        comments="",
        fmt="%.17g",
    )
    base = 'sample_time = 0.01\ndata = "d.csv"\n'
    ramp = read_experiment(
        _toml(
            tmp_path,
            base + 'kind = "closed_loop"\n[controller]\nkp = 10\n'
            '[reference]\nkind = "ramp"\nslope = 0.1\n',
        )
    )
    np.testing.assert_allclose(ramp.reference, 0.02 + 0.1 * t, rtol=0, atol=1e-15)
    assert ramp.controller == jc.PID(kp=10.0, sample_time=0.01)
    longer = ramp.experiment_for(0.2)  # a ramp continues; here 21 samples
    np.testing.assert_allclose(
        np.asarray(longer.signal), 0.02 + 0.1 * np.arange(21) * 0.01, rtol=0, atol=1e-15
    )
    volts = read_experiment(
        _toml(
            tmp_path, base + 'kind = "open_loop"\n[input]\nkind = "ramp"\nslope = 0.1\n', "b.toml"
        )
    )
    np.testing.assert_allclose(np.asarray(volts.experiment.signal), 0.1 * t, rtol=0, atol=1e-15)
    step = read_experiment(
        _toml(
            tmp_path,
            base + 'kind = "open_loop"\n[input]\nkind = "step"\namplitude = 1.5\n',
            "c.toml",
        )
    )
    assert step.experiment_for(0.05).n_samples == 6
    np.testing.assert_array_equal(np.asarray(step.experiment_for(0.3).signal), 1.5)


def test_build_plant_from_overrides():
    p = build_plant({"M": 1.25})
    assert float(p.m) == pytest.approx(1.25 + 0.1331, abs=1e-4)  # M + M_J (handout appendix)
    assert p.effects == ()  # the nominal plant: no amplifier limit, no friction
    p = build_plant({"f_c": 0.4, "v_sat": 5.0})
    assert p.effect(jc.Coulomb).f_c == 0.4 and p.effect(jc.Saturation).v_sat == 5.0
    assert p.structure == ("saturation", "coulomb")
    p = build_plant({"B_eq": 3.0}, base=jc.tap_plant())
    assert p.motor_connected is False and p.B_eq == 3.0 and p.effects == ()
    with pytest.raises(UserError, match="unknown plant parameter 'Beq'"):
        build_plant({"Beq": 3.0})


# ---------------------------------------------------------------- bad input

GOOD_CSV = "t,y,v\n0,0,1\n0.001,0.1,1\n0.002,0.2,1\n0.003,0.3,1\n"
HEAD = 'kind = "open_loop"\nsample_time = 0.001\ndata = "run.csv"\n'


def _mat(tmp_path):
    scipy.io.savemat(
        tmp_path / "a.mat", {"pos": np.zeros((4, 2)), "vv": np.zeros(3), "yy": np.zeros(4)}
    )


BAD = {
    "missing column": (HEAD, "t,pos,v\n0,0,1\n0.001,0,1\n", ["'y'", "pos", "run.csv"]),
    "misnamed column": (HEAD, "t,y,volt\n0,0,1\n0.001,0,1\n", ["'volt'", "run.csv", "[data]"]),
    "missing data file": ('kind = "tap"\ndata = "nope.csv"\n', None, ["nope.csv", "not found"]),
    "missing mat variable": (
        'kind = "tap"\n[data]\ny = "a.mat:y"\n',
        None,
        ["'y'", "a.mat", "pos", "[data] y"],
    ),
    "mat length mismatch": (
        'kind = "open_loop"\nsample_time = 0.001\n[data]\ny = "a.mat:yy"\nv = "a.mat:vv"\n',
        None,
        ["lengths", "a.mat:yy", "a.mat:vv", "4", "3"],
    ),
    "time not increasing": (HEAD, "t,y,v\n0,0,1\n0.001,0,1\n0.001,0,1\n", ["line 4", "t = 0.001"]),
    "nan sample": (HEAD, "t,y,v\n0,0,1\n0.001,nan,1\n0.002,0,1\n", ["column y", "line 3", "nan"]),
    "inf sample": (HEAD, "t,y,v\n0,0,1\n0.001,0,1\n0.002,0,inf\n", ["column v", "line 4", "inf"]),
    "not a number": (HEAD, "t,y,v\n0,0,1\n0.001,0,x1\n", ["line 3", "column v", "'x1'"]),
    "unknown key": ("sampletime = 0.001\n" + HEAD, GOOD_CSV, ["'sampletime'", "sample_time"]),
    "unknown controller key": (
        'kind = "closed_loop"\ndata = "run.csv"\n[controller]\nKp = 1\n'
        '[reference]\nkind = "step"\namplitude = 0.1\n',
        GOOD_CSV,
        ["'Kp'", "[controller]", "kp"],
    ),
    "unknown data key": ('kind = "tap"\n[data]\npos = "a.mat:pos"\n', None, ["'pos'", "[data]"]),
    "unknown reference key": (
        'kind = "closed_loop"\ndata = "run.csv"\n[reference]\nkind = "step"'
        "\namplitude = 0.1\nstart = 1\n",
        GOOD_CSV,
        ["'start'", "[reference]"],
    ),
    "unknown kind": ('kind = "closedloop"\ndata = "run.csv"\n', GOOD_CSV, ["kind", "'closedloop'"]),
    "zero mass": (
        HEAD + "[plant]\nM = 0\n",
        GOOD_CSV,
        ["[plant]", "M = 0", "out of its range [0.001"],
    ),
    "negative mass": (HEAD + "[plant]\nM = -1.0\n", GOOD_CSV, ["[plant]", "M = -1.0"]),
    "negative B_eq": (
        HEAD + "[plant]\nB_eq = -2.0\n",
        GOOD_CSV,
        ["[plant]", "B_eq = -2.0", "out of its range [0, 200] kg/s"],
    ),
    "unknown plant parameter": (
        HEAD + "[plant]\nBeq = 2.0\n",
        GOOD_CSV,
        ["[plant]", "'Beq'", "B_eq"],
    ),
    "zero sample_time": (HEAD.replace("0.001", "0"), GOOD_CSV, ["sample_time = 0.0", "positive"]),
    "negative sample_time": (HEAD.replace("0.001", "-0.001"), GOOD_CSV, ["sample_time = -0.001"]),
    "sample_time disagrees": (
        HEAD.replace("0.001", "0.00102"),
        GOOD_CSV,
        ["sample_time = 0.00102", "1 %", "line 3"],
    ),
    "bad gain": (
        'kind = "closed_loop"\ndata = "run.csv"\n[controller]\nkp = "fast"\n',
        GOOD_CSV,
        ["[controller] kp", "'fast'"],
    ),
    "bad derivative_on": (
        'kind = "closed_loop"\ndata = "run.csv"\n[controller]\nderivative_on = "output"\n',
        GOOD_CSV,
        ["derivative_on", "'output'"],
    ),
    "step without amplitude": (
        'kind = "closed_loop"\ndata = "run.csv"\n[reference]\nkind = "step"\n',
        GOOD_CSV,
        ["[reference]", "amplitude"],
    ),
    "no reference": ('kind = "closed_loop"\ndata = "run.csv"\n', GOOD_CSV, ["[reference]"]),
    "controller in open loop": (HEAD + "[controller]\nkp = 1\n", GOOD_CSV, ["[controller]"]),
    "toml syntax": ("kind = closed_loop\n", GOOD_CSV, ["not valid TOML", "line 1"]),
    "mat file as data": ('kind = "tap"\ndata = "a.mat"\n', None, ["a.mat", "[data]"]),
    # Files as spreadsheets and pandas save them: the message names the cause.
    "decimal commas": (HEAD, "t,y,v\n0,0,1,5\n0,001,0,1,5\n", ["line 2", "decimal commas"]),
    "quoted decimal commas": (HEAD, 't,y,v\n"0,0","0,0","1,5"\n', ["column t", "decimal commas"]),
    "excel separator line": (HEAD, "sep=,\nt,y,v\n0,0,1\n", ["line 1", "sep=", "delete"]),
    "pandas index column": (HEAD, ",t,y,v\n0,0,0,1\n1,0.001,0,1\n", ["index=False"]),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_input_is_one_line_naming_file_and_field(tmp_path, case):
    toml, csv, expected = BAD[case]
    _mat(tmp_path)
    if csv is not None:
        (tmp_path / "run.csv").write_text(csv)
    path = _toml(tmp_path, toml)
    with pytest.raises(UserError) as info:
        read_experiment(path)
    message = str(info.value)
    assert "\n" not in message and "exp.toml" in message
    for text in expected:
        assert text in message, (text, message)


def test_missing_experiment_file(tmp_path):
    with pytest.raises(UserError, match="nope.toml not found"):
        read_experiment(tmp_path / "nope.toml")


def test_write_rejects_bad_plant_overrides_and_batches(tmp_path):
    res = simulate(jc.handout_plant(), jc.PID(kp=20.0), jc.step(0.1, horizon=0.05))
    with pytest.raises(UserError, match=r"\[plant\].*M = -1.0"):
        write_experiment(tmp_path / "x.toml", res, plant_overrides={"M": -1.0})
    batch = dataclasses.replace(res, position=np.stack([res.position] * 2))
    with pytest.raises(UserError, match="one run at a time"):
        write_experiment(tmp_path / "y.toml", batch)
    assert not list(tmp_path.iterdir())


def test_csv_saved_by_excel_with_a_byte_order_mark(tmp_path):
    (tmp_path / "run.csv").write_bytes("\ufefft,y,v\r\n0,0,1\r\n0.001,0.1,1\r\n".encode("utf-8"))
    rec = read_experiment(_toml(tmp_path, HEAD))
    np.testing.assert_array_equal(rec.position, [0.0, 0.1])
    np.testing.assert_array_equal(rec.command, [1.0, 1.0])


# ---------------------------------------------------------------- large files (hw.csvio)


def test_csv_blocks_progress_and_exact_round_trip(tmp_path, monkeypatch, capsys):
    import hw.csvio as csvio

    rng = np.random.default_rng(7)
    n = 3000
    cols = {"t": np.arange(n) * 0.001, "y": rng.normal(size=n) * 0.1, "v": rng.normal(size=n)}
    with (tmp_path / "big.csv").open("w") as f:
        csvio.write_numeric_csv(f, list(cols), list(cols.values()), progress=lambda x: None)
    text = (tmp_path / "big.csv").read_text().splitlines()
    # A comment and a blank line in the middle: that block takes the csv module's path.
    text.insert(1500, "# operator note, 1, 2")
    text.insert(2000, "")
    (tmp_path / "big.csv").write_text("\n".join(text) + "\n")
    monkeypatch.setattr(csvio, "BLOCK", 1000)  # ~30 blocks, edges inside lines
    monkeypatch.setattr(csvio, "PROGRESS_BYTES", 1000)
    header, table, lines = csvio.read_numeric_csv(tmp_path / "big.csv", "big.csv")
    assert header == ["t", "y", "v"] and table.shape == (n, 3)
    for i, values in enumerate(cols.values()):  # shortest repr: every float read back exactly
        np.testing.assert_array_equal(table[:, i], values)
    assert lines[0] == 2 and lines[1498] == 1500 and lines[1499] == 1502 and lines[-1] == n + 3
    err = capsys.readouterr().err
    assert err.startswith("reading big.csv (") and " 100% in " in err and err.count("\n") == 1
    # A bad value far into the file: the same one-line error as the csv module's reading.
    text[2500] = text[2500].replace(",", ",x", 1)
    (tmp_path / "big.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(csvio.CSVError, match=r"big.csv line 2501, column y: 'x.*' is not a number"):
        csvio.read_numeric_csv(tmp_path / "big.csv", "big.csv", progress=lambda x: None)
    # A spreadsheet's regional export (semicolons, decimal commas) and a tab-separated one:
    # read as the CSV they stand for, line numbers and errors as in any other.
    for sep in (";", "\t"):
        text = f"# exported\nt{sep}y{sep}v\n0{sep}0,5{sep}1\n0,001{sep}-2,25e-3{sep}6\n"
        (tmp_path / "regional.csv").write_text(text)
        head, table, lines = csvio.read_numeric_csv(tmp_path / "regional.csv", "regional.csv")
        assert head == ["t", "y", "v"] and lines.tolist() == [3, 4]
        np.testing.assert_array_equal(table, [[0.0, 0.5, 1.0], [0.001, -2.25e-3, 6.0]])
        (tmp_path / "regional.csv").write_text(text + f"0,002{sep}x{sep}6\n")
        with pytest.raises(csvio.CSVError, match=r"regional.csv line 5, column y: 'x'"):
            csvio.read_numeric_csv(tmp_path / "regional.csv", "regional.csv")
    # Names and numbers separated by spaces (MATLAB's writematrix with a space, padded as
    # save -ascii pads, CRLF): the same, a bad value named as in any other (it was "column
    # 't y v': '0 0.5 1' is not a number"); where the names and the numbers do not count
    # alike ("cart position" over two numbers) it is not taken for a spaced table.
    text = "# exported\r\nt  y v\r\n   0  0.5   1 \r\n 0.001 -2.25e-3 6\r\n"
    (tmp_path / "spaced.txt").write_text(text, newline="")
    head, table, lines = csvio.read_numeric_csv(tmp_path / "spaced.txt", "spaced.txt")
    assert head == ["t", "y", "v"] and lines.tolist() == [3, 4]
    np.testing.assert_array_equal(table, [[0.0, 0.5, 1.0], [0.001, -2.25e-3, 6.0]])
    (tmp_path / "spaced.txt").write_text(text + "0.002 x 6\r\n", newline="")
    with pytest.raises(csvio.CSVError, match=r"spaced.txt line 5, column y: 'x'"):
        csvio.read_numeric_csv(tmp_path / "spaced.txt", "spaced.txt")
    # A logger's units line under the names: folded into them, where the reader converts a
    # unit it knows (it was "column time: 'ms' is not a number"); a second line of names is
    # no units line and stays an error.
    (tmp_path / "units.csv").write_text("time,y,volts,\n[ms],mm,V,\n0,0.5,1,\n1,-2.25,6,\n")
    head, table, lines = csvio.read_numeric_csv(tmp_path / "units.csv", "units.csv")
    assert head == ["time [ms]", "y [mm]", "volts [V]"] and lines.tolist() == [3, 4]
    np.testing.assert_array_equal(table, [[0.0, 0.5, 1.0], [1.0, -2.25, 6.0]])
    from hw.expfile import si_factor

    assert [si_factor(h) for h in head] == [1e-3, 1e-3, 1.0]
    # A title line above the names (it was "line 2: 3 fields, the header has 1").
    (tmp_path / "title.csv").write_text("P 50 step - run 3\nt,y,v\n0,0.5,1\n")
    head, table, lines = csvio.read_numeric_csv(tmp_path / "title.csv", "title.csv")
    assert head == ["t", "y", "v"] and lines.tolist() == [3] and table.tolist() == [[0, 0.5, 1]]
    (tmp_path / "dash.csv").write_text("t,y,v\n1,-,1\n")  # a missing value: no units line
    with pytest.raises(csvio.CSVError, match=r"dash.csv line 2, column y: '-'"):
        csvio.read_numeric_csv(tmp_path / "dash.csv", "dash.csv")
    (tmp_path / "names.csv").write_text("t,y,v\nTime,Position,Voltage\n0,0.5,1\n")
    with pytest.raises(csvio.CSVError, match=r"names.csv line 2, column t: 'Time'"):
        csvio.read_numeric_csv(tmp_path / "names.csv", "names.csv")
    (tmp_path / "odd.txt").write_text("time,cart position\n0 1\n")
    with pytest.raises(csvio.CSVError, match=r"odd.txt line 2: 1 fields, the header has 2"):
        csvio.read_numeric_csv(tmp_path / "odd.txt", "odd.txt")


@pytest.mark.parametrize("cell", ["", " ", "\t", "  \t "])
def test_blank_csv_cell_is_an_error_not_a_number(tmp_path, cell):
    # np.fromstring would read a cell of spaces as -1.0: the fast reader must not.
    from hw.csvio import CSVError, read_numeric_csv

    path = tmp_path / "blank.csv"
    path.write_text(f"t,y,v\n0,0,1\n0.001,{cell},1\n0.002,0,1\n")
    with pytest.raises(CSVError, match="line 3, column y"):
        read_numeric_csv(path, "blank.csv")


def test_csv_with_cr_only_line_ends_is_one_line(tmp_path):
    from hw.csvio import CSVError, read_numeric_csv

    path = tmp_path / "mac.csv"
    path.write_bytes(b"t,y,v\r0,0,1\r0.001,0,1\r")
    with pytest.raises(CSVError, match="CR only"):
        read_numeric_csv(path, "mac.csv")


def test_signal_read_without_x64_stays_float64():
    """A command reads its files before a fit turns x64 on: the recorded reference must not
    pass through float32 on the way (0.4 m would become 0.40000001 m)."""
    from pathlib import Path

    from tuning.estimation.fit import FitSettings, fit_segment

    path = Path(jc.__file__).parent / "data" / "p50.toml"
    with jax.enable_x64(False):
        rec = read_experiment(path)
    assert rec.experiment.signal.dtype == np.float32  # the JAX mode it was read in
    with jax.enable_x64(True):
        full = read_experiment(path)
        seg = fit_segment(rec, ["B_eq"], {}, FitSettings())
    np.testing.assert_array_equal(rec.signal64(), np.asarray(full.experiment.signal))
    assert rec.signal64().dtype == np.float64
    np.testing.assert_array_equal(np.asarray(seg.experiment.signal), rec.signal64())
    # Cut to another horizon, the signal keeps float64 too.
    with jax.enable_x64(True):
        longer = rec.experiment_for(4.0)
    assert np.asarray(longer.signal)[0] == rec.signal64()[0]


def test_csv_saved_differently_matlab_comments_and_units_in_the_header(tmp_path):
    """MATLAB's % comment lines are skipped like #; a header with the format's own units
    ("t [s],y [m],v [V]", "y (m)") reads as t, y, v; a column in mm, cm or ms by its header is
    converted (to 1e-15 relative); another unit is one line that says what to convert it to;
    positions in encoder counts are named so."""
    t = np.arange(400) * 0.001
    y = np.rint(0.02 * (1 - np.exp(-t / 0.05)) / 2.275e-5) * 2.275e-5
    body = "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(t, y, strict=True))
    tap = 'kind = "tap"\ndata = "run.csv"\n'
    (tmp_path / "run.csv").write_text("% tap, group 7, 2021-09-01\nt,y\n" + body + "% end\n")
    rec = read_experiment(_toml(tmp_path, tap))
    assert np.array_equal(rec.position, y) and np.array_equal(rec.time, t)
    for header in ("t [s],y [m]", "t (s), y (m)", "t[s],y[m]", "t_s,y_m"):
        (tmp_path / "run.csv").write_text(header + "\n" + body)
        assert np.array_equal(read_experiment(_toml(tmp_path, tap)).position, y)
    for header, ts, ys in (
        ("t [s],y [mm]", 1.0, 1e3),
        ("t_s,y_mm", 1.0, 1e3),
        ("t (ms),y (cm)", 1e3, 1e2),
        ("t_ms,y_m", 1e3, 1.0),
    ):
        scaled = "".join(f"{a * ts:.17g},{b * ys:.17g}\n" for a, b in zip(t, y, strict=True))
        (tmp_path / "run.csv").write_text(header + "\n" + scaled)
        rec = read_experiment(_toml(tmp_path, tap))
        np.testing.assert_allclose(rec.position, y, rtol=1e-15, atol=1e-20)
        np.testing.assert_allclose(rec.time, t, rtol=1e-15, atol=1e-20)
    (tmp_path / "run.csv").write_text("t [s],y [in]\n" + body)
    with pytest.raises(
        UserError,
        match=r"column 'y \[in\]' of run.csv is in 'in', a unit .*convert it to m and name",
    ):
        read_experiment(_toml(tmp_path, tap))
    # A column under another name: the hint maps the one that looks like it.
    (tmp_path / "run.csv").write_text("Position,Time\n" + body)
    with pytest.raises(UserError, match='map it in a \\[data\\] table \\(t = "run.csv:Time"\\)'):
        read_experiment(_toml(tmp_path, tap))
    # A column the format has no place for is not offered as the voltage (it was: v = ":current").
    extra = "".join(f"{a:.17g},{b:.17g},1.0\n" for a, b in zip(t, y, strict=True))
    (tmp_path / "run.csv").write_text("t,y,current\n" + extra)
    with pytest.raises(UserError, match="a column such as 'current' is then left out") as err:
        read_experiment(_toml(tmp_path, tap))
    assert "v = " not in str(err.value)
    (tmp_path / "run.csv").write_text("t,y,Voltage\n" + extra)
    with pytest.raises(UserError, match='map the columns .*v = "run.csv:Voltage"'):
        read_experiment(_toml(tmp_path, tap))
    counts = "".join(f"{a:.17g},{round(b / 2.275e-5) + 10000}\n" for a, b in zip(t, y, strict=True))
    (tmp_path / "run.csv").write_text("t,y\n" + counts)
    with pytest.raises(UserError, match="encoder counts\\? multiply by 2.275e-05"):
        read_experiment(_toml(tmp_path, tap))


def test_sample_time_written_with_its_unit(tmp_path):
    """sample_time = "1 ms" (or "0.001 s", "1000 us", "0.001") reads as 0.001 s exactly as the
    number does; a unit the reader does not convert, or no number, is one line that says what to
    give."""
    y = np.rint(0.02 * (1 - np.exp(-np.arange(400) * 0.001 / 0.05)) / 2.275e-5) * 2.275e-5
    t = np.arange(400) * 0.001
    body = "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(t, y, strict=True))
    (tmp_path / "run.csv").write_text("t,y\n" + body)
    plain = read_experiment(
        _toml(tmp_path, 'kind = "tap"\ndata = "run.csv"\nsample_time = 0.001\n')
    )
    for written in ('"1 ms"', '"0.001 s"', '"1000 us"', '"0.001"', '" 1ms "'):
        text = f'kind = "tap"\ndata = "run.csv"\nsample_time = {written}\n'
        rec = read_experiment(_toml(tmp_path, text))
        assert rec.sample_time == pytest.approx(plain.sample_time, rel=1e-12)
        assert np.array_equal(rec.position, plain.position)
    text = 'kind = "tap"\ndata = "run.csv"\nsample_time = "2 ms"\n'
    with pytest.raises(UserError, match=r"more than 1 % from sample_time = 0\.002 s"):
        read_experiment(_toml(tmp_path, text))
    for written in ('"1 min"', '"one ms"', '"1 ms 2"'):
        text = f'kind = "tap"\ndata = "run.csv"\nsample_time = {written}\n'
        with pytest.raises(UserError, match=r"sample_time = .*: give a number in s"):
            read_experiment(_toml(tmp_path, text))
