"""``python -m hw run`` / ``bench`` and ``jaxcart run``; hw in a process where jax and scipy
cannot be imported (the lab PC has numpy only)."""

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import hw
from hw.cli import main
from hw.control_law import PID
from hw.gains import write_gains
from jaxcart.files import read_experiment

ROOT = Path(__file__).resolve().parents[1]
PID_LAB = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
#: Run in a child: refuse every import of jax, jaxlib or scipy, then run the rest of argv.
BLOCKED = """
import sys, runpy
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('jax', 'jaxlib', 'scipy', 'jaxcart', 'tuning'):
            raise ImportError(f'{name} is blocked: hw must run with numpy only')
sys.meta_path.insert(0, Block())
"""


def _gains(tmp_path, pid=PID_LAB, name="gains.json"):
    return str(write_gains(tmp_path / name, pid, note="test"))


def test_run_on_the_sim_writes_a_recording(tmp_path, capsys):
    gains = _gains(tmp_path)
    out = tmp_path / "run.toml"
    args = ["run", gains, "--device", "sim", "--step", "0.3", "--duration", "0.5", "--virtual"]
    assert main(args + ["--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    rec = read_experiment(out)
    assert rec.n_samples == 501 and rec.controller == PID_LAB
    assert rec.meta["notes"]["gains"] == str(Path(gains).resolve())
    # Never over an existing recording: one line, exit status 2.
    assert main(args + ["--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err


def test_a_run_is_checked_against_the_prediction_its_gains_file_carries(tmp_path, capsys):
    """A gains file with a prediction (jaxcart lab writes one): the run's settling time against
    its band; outside it, the fitted value that would explain it; a run of another step is
    not compared (numpy only: hw.predicted)."""
    prediction = {
        "level": 0.9,
        "step": 0.5,
        "metrics": {
            "settling_time": {"nominal": 0.5, "band": [0.45, 0.55]},
            "overshoot": {"nominal": 0.0, "band": [0.0, 50.0]},
        },
        "sensitivity": {
            "v_sat": {"value": 5.5, "stderr": 0.3, "unit": "V", "settling_time": -0.2},
            "B_eq": {"value": 2.0, "stderr": 0.1, "unit": "kg/s", "settling_time": 0.001},
        },
    }
    pid = PID(kp=120.9, ki=1.67, kd=4.1, v_limit=6.0)  # settles in 0.725 s (docs/hardware.md)
    gains = str(write_gains(tmp_path / "g.json", pid, prediction=prediction))
    args = ["run", gains, "--device", "sim", "--virtual", "--out"]
    assert main([*args, str(tmp_path / "a.toml"), "--step", "0.5"]) == 0
    err = capsys.readouterr().err
    assert "against the prediction of the gains file" in err
    assert "settling time" in err and "OUTSIDE the predicted 90% band 0.450 s - 0.550 s" in err
    assert "would be explained by v_sat" in err and "B_eq" not in err.split("explained by")[1]
    assert main([*args, str(tmp_path / "b.toml"), "--step", "0.3"]) == 0
    assert "predicts a 0.5 m step; this run stepped to 0.3 m" in capsys.readouterr().err


def test_run_slider_plant_file_and_numbered_names(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    gains = _gains(tmp_path)
    (tmp_path / "cart.toml").write_text("B_eq = 4.6\nf_c = 0.45\n")
    args = ["run", gains, "--slider", "0.2,0,-0.2", "--hold", "0.3", "--virtual"]
    assert main(args + ["--plant", "cart.toml"]) == 0
    assert main(args) == 0
    first, second = capsys.readouterr().out.split()
    assert first.endswith("hw-run.toml") and second.endswith("hw-run-2.toml")
    rec = read_experiment(first)
    assert rec.n_samples == 901 and rec.meta["device"]["B_eq"] == 4.6
    assert list(rec.reference[[0, 300, 600, 900]]) == [0.2, 0.0, -0.2, -0.2]


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--step", "0.7"], "track limit"),
        (["--device", "q2_usb", "--virtual"], "real hardware"),
        (["--device", "replay"], "--replay"),
        (["--slider", "a,b"], "--slider"),
        (["--x-max", "-1"], "x_max"),
    ],
)
def test_run_refuses_bad_options_in_one_line(tmp_path, capsys, extra, words):
    assert main(["run", _gains(tmp_path), "--virtual", *extra]) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1, err


def test_run_refuses_gains_it_cannot_honour(tmp_path, capsys):
    gains = _gains(tmp_path, PID(kp=40.0, v_limit=12.0))
    assert main(["run", gains, "--virtual", "--out", str(tmp_path / "x")]) == 2
    assert "v_limit = 12 V" in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()


def test_a_fault_exits_1_and_is_recorded(tmp_path, capsys):
    gains = _gains(tmp_path)
    out = tmp_path / "f.toml"
    assert main(["run", gains, "--virtual", "--speed-max", "0.1", "--out", str(out)]) == 1
    assert "velocity limit" in capsys.readouterr().err
    assert read_experiment(out).meta["run"]["status"] == "fault"


def test_jaxcart_run_is_the_same_command(tmp_path):
    import argparse

    from tuning.commands import run as command

    parser = argparse.ArgumentParser()
    command.register(parser.add_subparsers(dest="command"))
    out = tmp_path / "j.toml"
    args = parser.parse_args(
        ["run", _gains(tmp_path), "--virtual", "--duration", "0.2", "--out", str(out)]
    )
    assert args.func(args) == 0 and read_experiment(out).n_samples == 201
    from jaxcart.errors import UserError

    with pytest.raises(UserError, match="exists"):
        args.func(args)


def test_every_hw_module_imports_without_jax_or_scipy():
    names = [m.name for m in pkgutil.walk_packages(hw.__path__, "hw.") if m.name != "hw.__main__"]
    assert {"hw.loop", "hw.safety", "hw.expfile", "hw.devices.sim", "hw.cli"} <= set(names)
    code = BLOCKED + f"import importlib\nfor n in {names!r}: importlib.import_module(n)\n"
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr


#: The child's loop on a clock the test drives (tests/fakeclock.py): paced as in real time,
#: judged late or not by that clock alone, never by the load of the machine running the tests.
FAKE_CLOCK = """
sys.path.insert(0, 'tests')
import hw.pacing, fakeclock
hw.pacing.SYSTEM_TIMER = fakeclock.FakeClock().timer
"""


def test_python_m_hw_run_in_real_time_with_numpy_only(tmp_path):
    gains = _gains(tmp_path)
    out = tmp_path / "np.toml"
    code = (
        BLOCKED
        + FAKE_CLOCK
        + "sys.argv = ['hw'] + sys.argv[1:]\nrunpy.run_module('hw', run_name='__main__')\n"
    )
    argv = [
        "run",
        gains,
        "--device",
        "sim",
        "--step",
        "0.2",
        "--duration",
        "0.3",
        "--watchdog",
        "0.1",
        "--real-time",
    ]
    done = subprocess.run(
        [sys.executable, "-c", code, *argv, "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    rec = read_experiment(out)
    assert rec.n_samples == 301 and rec.meta["device"]["clock"] == "perf_counter"
    assert "real time kept: every sample read within 500 us of its deadline" in done.stderr
    json.dumps(rec.meta["timing"])  # plain numbers


def test_bench_prints_both_loops(capsys):
    assert main(["bench", "--samples", "200"]) == 0
    out = capsys.readouterr().out
    assert "us/sample" in out and "naive time.sleep" in out and "overruns" in out


@pytest.mark.parametrize(
    "signals, code", [(["SIGTERM"], 143), (["SIGINT"] * 4, 130), (["SIGHUP"], 129)]
)
def test_a_real_signal_from_outside_stops_a_numpy_only_run(tmp_path, signals, code):
    """`python -m hw run` in a child with numpy only, in real time, sent real signals while it
    runs: 0 V, the recording finished with the reason, the conventional exit status. The
    signals go once the recording holds samples (not after a guessed time), and the loop's
    watchdog is off, so that a machine too busy for real time cannot stop the run first."""
    import signal
    import time

    gains = _gains(tmp_path)
    out = tmp_path / "sig.toml"
    code_text = (
        BLOCKED + "sys.argv = ['hw'] + sys.argv[1:]\nrunpy.run_module('hw', run_name='__main__')\n"
    )
    argv = ["run", gains, "--real-time", "--duration", "60", "--watchdog", "0"]
    child = subprocess.Popen(
        [sys.executable, "-c", code_text, *argv, "--out", str(out)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    first = child.stderr.readline()  # printed just before the loop starts
    assert "real time" in first, first
    csv = out.with_suffix(".csv")
    while not (csv.exists() and csv.read_text().count("\n") >= 3) and child.poll() is None:
        time.sleep(0.01)  # waiting for the first rows on disk (flushed every 100 samples)
    for name in signals:
        child.send_signal(getattr(signal, name))
        time.sleep(0.01)
    stdout, stderr = child.communicate(timeout=120)
    assert child.returncode == code, stderr
    rec = read_experiment(out)
    run = rec.meta["run"]
    assert run["status"] == "fault" and run["last_voltage"] == 0.0
    word = {"SIGINT": "Ctrl-C"}.get(signals[0], signals[0])
    assert word in run["fault"] and word in stderr
    assert 100 <= rec.n_samples < 60001 and "timing" in rec.meta  # stopped by the signal
    assert "Traceback" not in stderr  # later signals never cut the stop or the report short
