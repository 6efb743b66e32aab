"""Raw QUARC/Simulink .mat files in, without a hand-written TOML (issue 22 item 1): every scope
layout (structure with time, structure with empty time, N x 2 arrays, muxed scopes by column
or label, MATLAB v7.3/HDF5), the recorded error e = r - y through the reference, and each
recording's experiment recognised from its content and names, with a question where the
evidence is weak."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from jaxcart import matfile, matimport
from jaxcart.errors import UserError
from jaxcart.files import read_experiment

REAL = Path(__file__).resolve().parents[2] / "shared" / "realdata"
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
    raw = read_experiment(tmp_path / "run73.mat")  # no TOML: recognised
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
