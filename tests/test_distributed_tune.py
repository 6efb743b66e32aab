"""jaxcart tune --robust and jaxcart diagnose across processes (jax.distributed): two processes
on localhost on the CPU give the single-process result.

Each process holds two CPU devices, as this test process does (conftest), so each device
evaluates as many starts in both runs and the tuner's rows agree bit for bit. The diagnosis
splits 4 candidates 2 + 2 against 4 on one process: the per-device batch differs, so its
smooth fits may differ in the last bits (measured: 1e-12 relative); they are compared to 1e-8.

An error one process meets (patched in by the test's own code, run before the command line, or
an input only one process has) stops every process at once with the same one line.
"""

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cluster import spawn

import jaxcart as jc
from jaxcart.errors import UserError
from tuning import distributed
from tuning.design.start_share import StartShare

TAP = Path(jc.__file__).parent / "data" / "tap.toml"


def _wait(procs, codes=(0, 0), timeout_s=240):
    try:
        outs = [p.communicate(timeout=timeout_s) for p in procs]
    except subprocess.TimeoutExpired:
        for p in procs:  # none is left waiting for the hour of the store's timeout
            p.kill()
        raise
    for p, code, (_out, err) in zip(procs, codes, outs, strict=True):
        assert p.returncode == code, err[-2000:]
    return outs


def test_tune_robust_two_processes_equal_one(tmp_path):
    from tuning.design.losses import Spec
    from tuning.design.tune import tune

    argv = ["tune", "--robust", "--horizon", "1.5", "--iterations", "20", "--starts", "2"]
    procs = spawn(tmp_path, [*argv, "--quiet", "--out", "g.json", "--json", "r.json"])
    # Meanwhile the same problem in this process (the command's controller and spec).
    ref = tune(
        robust=True,
        n_starts=2,
        max_iterations=20,
        spec=Spec(horizon=1.5),
        controller=jc.PID(tau=0.01, v_limit=6.0, sample_time=0.001),
    )
    outs = _wait(procs)
    assert outs[1][0].strip() == "process 1 of 2: done, results sent to process 0"
    assert not list((tmp_path / "p1").iterdir())  # only process 0 writes outputs
    assert "over 2 processes" in outs[0][0]
    doc = json.loads((tmp_path / "p0" / "r.json").read_text())
    for name in ("kp", "kd", "ki"):
        np.testing.assert_allclose(doc["gains"][name], getattr(ref.gains, name), rtol=1e-9)
    assert doc["worst"]["settling_time"] == pytest.approx(ref.worst.settling_time, abs=1e-12)
    assert doc["iterations"] == ref.iterations and doc["meets"] == ref.meets


def test_diagnose_two_processes_equal_one(tmp_path):
    from jaxcart.files import read_experiment
    from tuning.estimation.diagnose import diagnose

    procs = spawn(tmp_path, ["diagnose", str(TAP), "--quiet", "--out", "d", "--json", "d.json"])
    ref = diagnose([read_experiment(TAP)], progress=False)
    outs = _wait(procs)
    assert "results sent to process 0" in outs[1][0]
    assert not list((tmp_path / "p1").iterdir())
    doc = json.loads((tmp_path / "p0" / "d.json").read_text())
    assert doc["chosen"] == ref.chosen and doc["left_out"] == ref.left_out
    assert doc["equivalent"] == ref.equivalent
    got = {c["name"]: c for c in doc["candidates"]}
    assert set(got) == {c.name for c in ref.candidates}
    for c in ref.candidates:
        np.testing.assert_allclose(got[c.name]["score"], c.score, rtol=1e-8, err_msg=c.name)
        for k, v in c.values.items():
            if "@" not in k:
                np.testing.assert_allclose(got[c.name]["values"][k], v, rtol=1e-8, err_msg=k)
    for n, p in ref.parameters.items():
        np.testing.assert_allclose(doc["parameters"][n]["value"], p["value"], rtol=1e-8)


def test_every_start_and_row_has_one_owner():
    # No runtime needed: the shares of 3 processes cover 7 starts once each.
    shares = [StartShare(7, i, 3) for i in range(3)]
    rows = np.sort(np.concatenate([s.rows for s in shares]))
    np.testing.assert_array_equal(rows, np.arange(7))
    parts = [{"x": np.asarray(s.rows, float) * 10} for s in shares]
    whole = distributed.gather_rows(parts, shares[0].owners(7), 7)
    np.testing.assert_array_equal(whole["x"], np.arange(7) * 10.0)
    with pytest.raises(UserError, match="at least one start each; give --starts 3"):
        StartShare(2, 2, 3)


def test_bad_options_fail_before_joining(tmp_path, capsys, monkeypatch):
    from tuning.commands.main import main

    monkeypatch.chdir(tmp_path)
    cluster = ["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "0"]
    assert main(["tune", "--compare", *cluster]) == 2
    assert "--compare runs in one process" in capsys.readouterr().err
    # Process 0's outputs are checked before it joins (nobody listens on port 1: a join would
    # fail with another message, after the runtime's timeout).
    (tmp_path / "g.json").write_text("{}")
    assert main(["tune", "--robust", "--out", "g.json", *cluster]) == 2
    assert "g.json exists" in capsys.readouterr().err
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "report.md").write_text("")
    assert main(["diagnose", str(TAP), "--out", "d", *cluster]) == 2
    assert "report.md exists" in capsys.readouterr().err


#: Run first by each process of the tests below: a failure where JAXCART_PROCESS_ID is 1.
FAIL_ON_1 = """
import os
if os.environ["JAXCART_PROCESS_ID"] == "1":
{}
"""
#: The tuner's 4th iteration fails on process 1 (a bug's exception, not a UserError).
TUNE_FAILS = FAIL_ON_1.format(
    """    import tuning.design.iteration as T
    entry = T._history_entry
    def _history_entry(it, *rest):
        if it == 3:
            raise RuntimeError("injected at iteration 3")
        return entry(it, *rest)
    T._history_entry = _history_entry"""
)
#: Process 1's exact polishes fail (after the first batch fit and exact re-checks).
DIAGNOSE_FAILS = FAIL_ON_1.format(
    """    import tuning.estimation.diagnose.candidate_runs as D
    from jaxcart.errors import SimulationDiverged
    def polish(*args, **kwargs):
        raise SimulationDiverged("injected: the exact polish diverged")
    D.polish = polish"""
)


def _stopped(procs, command, message):
    """Every process exited within 60 s with ``message`` as its one error line (a process
    that waits for its partner would wait up to an hour)."""
    outs = _wait(procs, codes=(2, 2), timeout_s=60)
    for _out, err in outs:
        assert err.strip().splitlines()[-1] == f"jaxcart {command}: error: {message}", err[-2000:]


def test_tune_error_on_one_process_stops_every_one(tmp_path):
    argv = ["tune", "--horizon", "1.5", "--iterations", "20", "--starts", "2", "--quiet"]
    procs = spawn(tmp_path, [*argv, "--out", "g.json"], inject=TUNE_FAILS)
    _stopped(procs, "tune", "RuntimeError in process 1 of 2: injected at iteration 3")
    assert not list((tmp_path / "p0").iterdir())  # process 0 wrote nothing


def test_diagnose_error_on_one_process_stops_every_one(tmp_path):
    argv = ["diagnose", str(TAP), "--quiet", "--out", "d"]
    procs = spawn(tmp_path, argv, inject=DIAGNOSE_FAILS)
    _stopped(procs, "diagnose", "injected: the exact polish diverged")
    assert not list((tmp_path / "p0").iterdir())


def test_diagnose_input_only_one_process_has_stops_every_one(tmp_path):
    # The recording is in process 0's folder only: process 1 fails to read it, and process
    # 0 stops at the exchange after the inputs, before it compiles anything.
    (tmp_path / "p0").mkdir()
    for name in ("tap.toml", "tap.csv"):
        shutil.copy(TAP.parent / name, tmp_path / "p0" / name)
    procs = spawn(tmp_path, ["diagnose", "tap.toml", "--quiet", "--out", "d"])
    outs = _wait(procs, codes=(2, 2), timeout_s=30)
    errors = {err.strip().splitlines()[-1] for _out, err in outs}
    assert len(errors) == 1 and "tap.toml" in errors.pop(), errors
    assert not (tmp_path / "p0" / "d").exists()
