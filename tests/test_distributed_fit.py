"""jaxcart fit --cross across processes (jax.distributed): two processes on localhost on the
CPU give the single-process report (tuning/estimation/cross_fit.py).

Each process fits one of the two built-in recordings alone and predicts the other with it; the
test process computes the single-process table meanwhile. Each process holds two CPU devices, as
this test process does (conftest), and a fit of one recording is the same computation in
both, so the numbers agree bit for bit (measured); they are compared to 1e-12 relative, which
leaves room for nothing but last-bit noise: a wrong split, order or exchange moves an RMS by
percent. The commands run without x64 at the start, this process with it: the recordings'
signals are read in float64 all the same (Recording.signal), or the closed loop's RMS would
move by 1e-7 relative.
"""

import json
from pathlib import Path

import numpy as np
from cluster import in_threads, spawn

import jaxcart as jc
from jaxcart.errors import UserError
from tuning.estimation import cross_fit

DATA = Path(jc.__file__).parent / "data"
RECORDINGS = [str(DATA / "tap.toml"), str(DATA / "p50.toml")]
#: One parameter keeps each of the six fits at about a second.
ARGV = ["fit", *RECORDINGS, "--cross", "--params", "B_eq", "--quiet", "--json", "r.json"]


def test_fit_cross_two_processes_equal_one(tmp_path):
    from jaxcart.files import read_experiment

    procs = spawn(tmp_path, ARGV)
    # Meanwhile, in this process, the rows process 1 computed and sent (p50.toml fitted
    # alone): those of process 0 are the same function on the same data, and the test's
    # budget has no room for them (the compilation dominates, repeated in every process).
    recordings = [read_experiment(p) for p in RECORDINGS]
    want = cross_fit.cross_rows(recordings[1], recordings, ("B_eq",))
    outs = [p.communicate(timeout=240) for p in procs]
    for p, (_out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-2000:]
    assert outs[1][0].strip() == "process 1 of 2: done, results sent to process 0"
    assert not list((tmp_path / "p1").iterdir())  # only process 0 writes outputs
    assert "each recording fitted by one of 2 processes" in outs[0][0]
    doc = json.loads((tmp_path / "p0" / "r.json").read_text())
    assert doc["params"]["B_eq"]["value"] > 0  # process 0 ran the joint fit and wrote it
    got = doc["cross_prediction"]
    # Every row, in the single-process order: grouped by the recording fitted.
    assert [(r["fitted_on"], r["predicting"]) for r in got] == [
        ("tap.toml", "tap.toml"),
        ("tap.toml", "p50.toml"),
        ("p50.toml", "tap.toml"),
        ("p50.toml", "p50.toml"),
    ]
    for g, w in zip(got[2:], want, strict=True):
        what = f"{g['fitted_on']} -> {g['predicting']}"
        assert (g["fitted_on"], g["predicting"], g["held"]) == (
            w["fitted_on"],
            w["predicting"],
            w["held"],
        )
        np.testing.assert_allclose(g["values"]["B_eq"], w["values"]["B_eq"], rtol=1e-12)
        np.testing.assert_allclose(g["rms"], w["rms"], rtol=1e-12, err_msg=what)
        np.testing.assert_allclose(g["rms_smooth"], w["rms_smooth"], rtol=1e-12, err_msg=what)
    # The two recordings disagree (a tap and a closed loop, f_c left out): each
    # cross-prediction is worse than the own fit, so the rows are not copies of one another.
    own = {r["fitted_on"]: r["rms"] for r in got if r["fitted_on"] == r["predicting"]}
    for r in got:
        if r["fitted_on"] != r["predicting"]:
            assert r["rms"] > own[r["predicting"]]


def test_a_failure_anywhere_is_raised_on_every_process(monkeypatch):
    # Processes as threads (tests/cluster.py); the rows of recording "b" cannot be computed.
    def rows(rec, recordings, params, **kwargs):
        return [{"fitted_on": rec}] if rec == "a" else [{"fitted_on": rec, "rms": 1 / 0}]

    monkeypatch.setattr(cross_fit, "cross_rows", rows)

    def table(failure=None):
        def work(ex):
            return cross_fit.cross_table(
                ["a", "b"], ("B_eq",), processes=ex, failure=failure if ex.index == 0 else None
            )

        return in_threads(monkeypatch, work)

    # Process 1 could not fit its recording: process 0 raises its error too instead of
    # writing a table with a hole.
    for exc in table():
        assert type(exc) is UserError
        assert str(exc) == "ZeroDivisionError in process 1 of 2: division by zero"
    # Process 0's joint fit failed: it computes no rows, and its error, from before the
    # table, wins over a row's.
    assert {str(e) for e in table(UserError("joint fit failed"))} == {"joint fit failed"}
    monkeypatch.setattr(cross_fit, "cross_rows", lambda rec, *a, **k: [{"fitted_on": rec}])
    assert table() == [[{"fitted_on": "a"}, {"fitted_on": "b"}]] * 2


def test_bad_options_fail_before_joining(tmp_path, capsys, monkeypatch):
    from tuning.commands.main import main

    monkeypatch.chdir(tmp_path)
    cluster = ["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "0"]
    # Process 0's outputs are checked before it joins (nobody listens on port 1: a join
    # would fail with another message, after the runtime's timeout).
    (tmp_path / "r.json").write_text("{}")
    assert main([*ARGV, *cluster]) == 2
    assert "r.json exists" in capsys.readouterr().err
    assert main(["fit", RECORDINGS[0], "--cross", *cluster]) == 2
    assert "--cross needs at least two recordings" in capsys.readouterr().err
