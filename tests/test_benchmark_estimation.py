"""The estimation benchmark (python -m tuning.benchmark.estimation): its machinery, not its
times: the timer's CPU seconds and exit statuses, the joint case's cart, the check of a
diagnosis against that cart's truth, the table and the options."""

import sys
from pathlib import Path

import numpy as np
import pytest

from jaxcart.effects import Coulomb, Saturation
from jaxcart.files import read_experiment
from tuning.benchmark import estimation, startup
from tuning.estimation.diagnose.structures import PER_RUN


def test_timed_counts_the_childs_cpu_seconds_and_checks_its_exit_status():
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass"
    t = startup.timed([sys.executable, "-c", busy], startup._env(Path("unused")))
    # The child spun for 0.3 s of CPU; its interpreter's start adds a little, never removes.
    assert 0.3 <= t.cpu < 0.3 + t.wall
    assert t.wall >= 0.3 and t.returncode == 0
    fails = [sys.executable, "-c", "import sys; sys.exit(1)"]
    assert startup.timed(fails, {}, ok=(0, 1)).returncode == 1
    with pytest.raises(RuntimeError, match="failed"):
        startup.timed(fails, {})


def test_builtin_recordings_are_found():
    assert Path(startup._data("p50")).is_file() and Path(startup._data("tap")).is_file()


def test_the_joint_cart_is_a_tap_and_four_runs_each_reaching_its_own_limit(tmp_path):
    paths = estimation.write_cart(tmp_path)
    recordings = [read_experiment(p) for p in paths]
    assert [r.kind for r in recordings] == ["tap"] + ["closed_loop"] * len(estimation.RUNS)
    assert len({run.v_sat for run in estimation.RUNS}) == len(estimation.RUNS)
    for rec, run in zip(recordings[1:], estimation.RUNS, strict=True):
        # The recorded command passes v_sat for at least 0.1 s, so the limit shows in the run.
        above = np.abs(rec.command) > run.v_sat
        assert above.sum() * rec.sample_time >= 0.1, run.stem
        assert "v_sat" not in rec.meta.get("description", "")  # the truth is not in the file


def test_check_joint_compares_named_effects_and_per_run_limits_with_the_truth():
    limit = Saturation.params[0].name
    per_recording = {
        f"/tmp/x/{run.stem}.toml": {"parameters": {limit: {"value": run.v_sat + 0.01}}}
        for run in estimation.RUNS[:-1]
    }
    diagnosis = {
        "status": "diagnosed",
        "verdict": "explained",
        "left_out": [Coulomb.name],
        "chosen": f"{PER_RUN}+{Coulomb.name}",
        "parameters": {"B_eq": {"value": 3.8}},
        "per_recording": per_recording,
    }
    check = estimation.check_joint(diagnosis)
    assert check["named"] == {Coulomb.name: True, Saturation.name: False, PER_RUN: True}
    first, last = estimation.RUNS[0], estimation.RUNS[-1]
    assert check["per_run"][first.stem] == (pytest.approx(first.v_sat + 0.01), first.v_sat)
    assert check["per_run"][last.stem] == (None, last.v_sat)
    assert check["shared"]["B_eq"] == (3.8, estimation.CART["B_eq"])
    assert check["shared"]["f_c"] == (None, estimation.CART["f_c"])
    text = estimation._joint_lines(check)
    assert f"{Saturation.name} NO" in text[1] and "not fitted" in text[-1]


def test_table_marks_medians_against_the_targets():
    def runs(*walls):
        return [startup.Timing(w, w / 2, "", 0) for w in walls]

    rows = [
        estimation.Row("single", "built-in p50", "warm", runs(20.0, 10.0, 12.0)),
        estimation.Row("lab", "built-in data", "cold", runs(50.0, 60.0, 55.0)),
    ]
    text = estimation.table({"rows": rows, "load": {"start": (1, 2, 3), "end": (2, 2, 3)}})
    single, lab = text.splitlines()[1:3]
    assert "12.0" in single and "6.0" in single and "met" in single  # median, CPU median
    assert "55.0" in lab and "MISSED" in lab
    assert "load average" in text


def test_options_are_checked():
    with pytest.raises(SystemExit):
        estimation.main(["--only", "single,bogus"])
    with pytest.raises(SystemExit):
        estimation.main(["--repeats", "0"])
