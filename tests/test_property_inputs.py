"""Random damage to valid experiment files (hypothesis): every command either succeeds or prints
one error line, never a traceback; and the fast CSV reader (hw.csvio) reads any text exactly as
the csv module's reading of the documented rules does.

derandomize=True (the same examples on every run, so CI is reproducible), no example database,
small max_examples: the budget of the whole file is about 20 s on the shared 2-core CPU.
"""

import csv
import io
import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hw.csvio import CSVError, read_numeric_csv
from jaxcart.errors import UserError
from jaxcart.files import read_experiment
from tuning.commands.main import main

SETTINGS = dict(
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
#: simulate always runs this horizon, so that every example reuses one compiled program.
HORIZON = "0.2"


# ---------------------------------------------------------------- the valid files


def _base_rows(n=120, ts=0.001):
    t = np.arange(n) * ts
    y = 0.1 * (1 - np.exp(-t / 0.2))  # 0.5 m/s at most: a motion the cart can make
    y = np.round(y / 2.275e-5) * 2.275e-5
    v = np.clip(20.0 * (0.1 - y), -6, 6)
    return t, y, v


BASE_TOML = {
    "kind": "closed_loop",
    "sample_time": 0.001,
    "data": "run.csv",
    "controller": {"kp": 20.0, "v_limit": 6.0},
    "reference": {"kind": "step", "amplitude": 0.1},
}


def _base_csv() -> str:
    t, y, v = _base_rows()
    rows = zip(t.tolist(), y.tolist(), v.tolist(), strict=True)
    lines = ["t,y,v"] + [f"{a!r},{b!r},{c!r}" for a, b, c in rows]
    return "\n".join(lines) + "\n"


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(value)


def _toml_text(meta: dict) -> str:
    top = [f"{k} = {_toml_value(v)}" for k, v in meta.items() if not isinstance(v, dict)]
    tables = []
    for k, v in meta.items():
        if isinstance(v, dict):
            tables += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(top + tables) + "\n"


# ---------------------------------------------------------------- mutations

VALUES = st.one_of(
    st.sampled_from([0.0, -1.0, 1e300, -1e-300, math.nan, math.inf, -math.inf, 1e6, -100.0]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-10, 10),
    st.booleans(),
    st.sampled_from(["", "step", "ramp", "column", "tap", "open_loop", "run.csv", "x.mat:y"]),
    st.text(max_size=5),
    st.lists(st.floats(-2, 2), max_size=3),
)
KEYS = st.sampled_from(
    [
        "kind",
        "sample_time",
        "data",
        "initial_velocity",
        "description",
        "bogus",
        "kp",
        "ki",
        "kd",
        "tau",
        "kb",
        "v_limit",
        "derivative_on",
        "anti_windup",
        "amplitude",
        "slope",
        "f_c",
        "B_eq",
        "v_sat",
        "M",
    ]
)
#: Where a mutation lands: mostly the tables the file has, sometimes one that does not belong.
TABLES = st.sampled_from(
    [None, "controller", "controller", "reference", "plant", "plant", "input", "tap", "data"]
)
OWN_KEYS = {
    "controller": st.sampled_from(
        ["kp", "ki", "kd", "tau", "kb", "v_limit", "derivative_on", "anti_windup"]
    ),
    "reference": st.sampled_from(["kind", "amplitude", "slope"]),
    "plant": st.sampled_from(["f_c", "B_eq", "v_sat", "M", "bogus"]),
}
NUMBERS = st.one_of(
    st.sampled_from([0.0, 0.5, 2.0, 10.0, 100.0]), st.floats(-1e3, 1e3, allow_nan=False)
)


@st.composite
def toml_mutations(draw):
    meta = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE_TOML.items()}
    for _ in range(draw(st.integers(1, 2))):
        table = draw(TABLES)
        own = OWN_KEYS.get(table)
        key = draw(own if own is not None and draw(st.booleans()) else KEYS)
        target = meta if table is None else meta.setdefault(table, {})
        if not isinstance(target, dict):
            continue
        if draw(st.booleans()) and key in target:
            del target[key]
        else:
            target[key] = draw(NUMBERS if draw(st.booleans()) else VALUES)
    text = _toml_text(meta)
    if draw(st.integers(0, 4)) == 0:  # a syntax error somewhere
        i = draw(st.integers(0, len(text) - 1))
        text = text[:i] + draw(st.sampled_from(["=", "[", '"', "\n", "", "#"])) + text[i + 1 :]
    return text


CELLS = st.sampled_from(
    [
        "",
        "abc",
        "nan",
        "inf",
        "-inf",
        "1e400",
        "-0",
        " 1 ",
        '"2"',
        "0x10",
        "1_0",
        "1e-3",
        "402.5",
        "1;2",
        "\t",
        "1.2.3",
        "+.5",
        "ÿ",
        "1e308",
        "-1.7e308",
    ]
)


@st.composite
def csv_mutations(draw, base=None):
    lines = (base or _base_csv()).splitlines()
    for _ in range(draw(st.integers(1, 2))):
        what = draw(
            st.sampled_from(
                [
                    "cell",
                    "drop_row",
                    "dup_row",
                    "swap",
                    "drop_col",
                    "rename",
                    "bom",
                    "delim",
                    "crlf",
                    "blank",
                    "comment",
                    "truncate",
                    "empty",
                    "scale_y",
                    "extra_field",
                ]
            )
        )
        i = draw(st.integers(0, len(lines) - 1)) if lines else 0
        if what == "cell" and lines:
            row = lines[i].split(",")
            row[draw(st.integers(0, len(row) - 1))] = draw(CELLS)
            lines[i] = ",".join(row)
        elif what == "drop_row" and lines:
            del lines[i]
        elif what == "dup_row" and lines:
            lines.insert(i, lines[i])
        elif what == "swap" and len(lines) > 2:
            j = draw(st.integers(1, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif what == "drop_col" and lines:
            j = draw(st.integers(0, 2))
            lines = [",".join(c for k, c in enumerate(line.split(",")) if k != j) for line in lines]
        elif what == "rename" and lines:
            lines[0] = draw(st.sampled_from(["t,y,V", "time,y,v", "t,y,y", "t, y ,v", "t,y"]))
        elif what == "bom" and lines:
            lines[0] = "\ufeff" + lines[0]
        elif what == "delim":
            sep = draw(st.sampled_from([";", "\t", " "]))
            lines = [line.replace(",", sep) for line in lines]
        elif what == "crlf":
            lines = [line if line.endswith("\r") else line + "\r" for line in lines]
        elif what == "blank":
            lines.insert(i, draw(st.sampled_from(["", "   ", ",,"])))
        elif what == "comment":
            lines.insert(i, "# a note, with a comma")
        elif what == "truncate" and lines:
            lines = lines[: i + 1]
            lines[-1] = lines[-1][: draw(st.integers(0, len(lines[-1])))]
        elif what == "empty":
            lines = []
        elif what == "scale_y" and lines:  # positions in mm
            rows = [line.split(",") for line in lines[1:]]
            rows = [r[:1] + [_times(r[1], 1000)] + r[2:] if len(r) > 1 else r for r in rows]
            lines = lines[:1] + [",".join(r) for r in rows]
        elif what == "extra_field" and lines:
            lines[i] += ",1"
    return "\n".join(lines) + ("\n" if draw(st.booleans()) else "")


def _times(text, factor):
    try:
        return repr(float(text) * factor)
    except ValueError:
        return text


# ---------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("property")


_count = [0]


def _run(argv, capsys):
    """main(argv) must return 0, or 2 with exactly one error line; never raise."""
    capsys.readouterr()
    try:
        status = main(argv)
    except SystemExit as exc:  # argparse on a bad option: its own usage line + error line
        status = exc.code
    except Exception as exc:  # noqa: BLE001 - the property: nothing escapes as a traceback
        pytest.fail(f"{argv}: {type(exc).__name__}: {exc}")
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if ": error:" in line]

    assert "Traceback" not in err
    if status == 0:
        assert errors == [], err
    else:
        assert status == 2 and len(errors) == 1, err
        assert errors[0] == err.splitlines()[-1]
    return status


def _write(folder, toml_text, csv_text):
    _count[0] += 1
    name = f"e{_count[0]}"
    (folder / "run.csv").write_text(csv_text, encoding="utf-8", newline="")
    path = folder / f"{name}.toml"
    path.write_text(toml_text, encoding="utf-8")
    return path, folder / f"{name}-out.csv"


#: One file damaged at a time, or both: most examples then fail in one place, some succeed.
DAMAGED = st.one_of(
    st.tuples(toml_mutations(), st.just(_base_csv())),
    st.tuples(st.just(_toml_text(BASE_TOML)), csv_mutations()),
    st.tuples(toml_mutations(), csv_mutations()),
)


def test_the_undamaged_file_simulates(folder, capsys):
    path, out = _write(folder, _toml_text(BASE_TOML), _base_csv())
    assert _run(["simulate", str(path), "--horizon", HORIZON, "--out", str(out)], capsys) == 0


@settings(max_examples=30, **SETTINGS)
@given(texts=DAMAGED)
def test_simulate_succeeds_or_prints_one_line(folder, capsys, texts):
    toml_text, csv_text = texts
    path, out = _write(folder, toml_text, csv_text)
    argv = ["simulate", str(path), "--horizon", HORIZON, "--out", str(out), "--force"]
    _run(argv + ["--plot", str(folder / "p.png")] if _count[0] % 10 == 0 else argv, capsys)


@settings(max_examples=40, **SETTINGS)
@given(texts=DAMAGED)
def test_reading_any_damaged_file_is_a_recording_or_one_line(folder, capsys, texts):
    toml_text, csv_text = texts
    path, out = _write(folder, toml_text, csv_text)
    try:
        rec = read_experiment(path)
    except UserError as exc:
        assert "\n" not in str(exc) and str(exc)
        # fit reads through the same path: the same one line, before any computing (a fit
        # that runs costs ~15 s, beyond this file's budget).
        fit = ["fit", str(path), "--params", "B_eq", "--out", str(out.with_suffix(".toml"))]
        assert _run(fit, capsys) == 2
        return
    assert np.all(np.isfinite(rec.position)) and rec.n_samples >= 2


MAT_VARIABLES = st.sampled_from(
    [
        "array",
        "row",
        "vector",
        "scope",
        "scope_no_time",
        "no_signals",
        "text",
        "empty",
        "matrix",
        "short_time",
        "mm",
    ]
)


def _mat_variable(kind):
    t, y, _ = _base_rows()
    scope = {"time": t[:, None], "signals": {"values": y[:, None], "dimensions": 1}}
    return {
        "array": np.column_stack([t, y]),
        "row": np.vstack([t, y]),
        "vector": y,
        "scope": scope,
        "scope_no_time": {"time": np.zeros((0, 0)), "signals": {"values": y[:, None]}},
        "no_signals": {"time": t[:, None]},
        "text": "not numbers",
        "empty": np.zeros((0,)),
        "matrix": np.ones((5, 7)),
        "short_time": {"time": t[:10, None], "signals": {"values": y[:, None]}},
        "mm": np.column_stack([t, 1000 * y]),
    }[kind]


@settings(max_examples=20, **SETTINGS)
@given(
    kind=MAT_VARIABLES,
    name=st.sampled_from(["y", "y", "y", "pos"]),
    ts=st.sampled_from([None, 0.001, 0.01]),
)
def test_mat_variables_read_or_one_line(folder, capsys, kind, name, ts):
    scipy.io.savemat(folder / "run.mat", {name: _mat_variable(kind)})
    text = 'kind = "tap"\n' + (f"sample_time = {ts}\n" if ts else "") + '[data]\ny = "run.mat:y"\n'
    _count[0] += 1
    path = folder / f"m{_count[0]}.toml"
    path.write_text(text)
    try:
        read_experiment(path)
    except UserError as exc:
        assert "\n" not in str(exc)
    if _count[0] % 5 == 0:
        out = folder / f"m{_count[0]}-out.csv"
        _run(["simulate", str(path), "--horizon", HORIZON, "--out", str(out), "--force"], capsys)


# ---------------------------------------------------------------- the fast CSV reader


def _reference_read(text: str, name="run.csv"):
    """The documented rules with the csv module, row by row (the reader before hw.csvio): a
    first line of numbers is no header, a comma ending every line no column."""
    header, rows, lines = None, [], []
    if text.startswith("\ufeff"):
        text = text[1:]
    for lineno, row in enumerate(csv.reader(io.StringIO(text, newline="")), start=1):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        if header is None:
            header = [h.strip() for h in row]
            sep = next((c for c in ";\t" if len(header) == 1 and c in header[0]), None)
            if sep is not None:  # a regional export: its commas decimal points
                return _reference_read(text.translate(str.maketrans({",": ".", sep: ","})), name)
            words = header[0].split() if len(header) == 1 else [h for h in header if h]
            if words and all(_is_number(w) for w in words):
                raise CSVError(f"{name} line {lineno}: numbers, no header")
            if len(header) > 1 and header[-1] == "":  # a trailing comma: no column
                header = header[:-1]
            continue
        if len(row) == len(header) + 1 and not row[-1].strip():
            row = row[:-1]  # a trailing comma
        if len(row) != len(header):
            raise CSVError(f"{name} line {lineno}: {len(row)} fields")
        try:
            rows.append([float(x) for x in row])
        except ValueError:
            raise CSVError(f"{name} line {lineno}, column") from None
        lines.append(lineno)
    return header, rows, lines


def _is_number(text) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


@settings(max_examples=150, **SETTINGS)
@given(text=csv_mutations(), block=st.sampled_from([64, 256, 1 << 22]))
def test_fast_csv_reader_agrees_with_the_csv_module(tmp_path_factory, monkeypatch, text, block):
    import hw.csvio

    monkeypatch.setattr(hw.csvio, "BLOCK", block)  # block edges inside lines and rows
    path = Path(tmp_path_factory.getbasetemp()) / "fast.csv"
    path.write_bytes(text.encode("utf-8"))
    try:
        expected = _reference_read(text)
    except CSVError as exc:
        with pytest.raises(CSVError) as err:
            read_numeric_csv(path, "run.csv", progress=lambda f: None)
        # The same line is named.
        assert (
            re.match(r"run.csv line \d+", str(err.value))[0]
            == re.match(r"run.csv line \d+", str(exc))[0]
        )
        return
    header, table, lines = read_numeric_csv(path, "run.csv", progress=lambda f: None)
    assert header == expected[0]
    if header is not None:
        want = np.asarray(expected[1], dtype=float).reshape(len(expected[1]), len(header))
        np.testing.assert_array_equal(table, want)
        assert lines.tolist() == expected[2]


def test_tomllib_round_trip_of_the_base_file():
    # The mutations start from a valid file that the serializer writes as TOML.
    assert tomllib.loads(_toml_text(BASE_TOML)) == BASE_TOML
