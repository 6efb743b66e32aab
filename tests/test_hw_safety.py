"""Every safety path of the loop, injected: it ends with 0 V written, the device stopped and a
recording that says why."""

import numpy as np
import pytest
from fakeclock import FakeClock

from hw.control_law import PID
from hw.devices.base import DeviceError
from hw.devices.sim import CartParams, SimCart
from hw.loop import run_loop
from hw.safety import Limits
from jaxcart.files import read_experiment

PID_LAB = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)


class Injected(SimCart):
    """The simulated cart with something going wrong at read number ``at``."""

    def __init__(self, action, at=100, **params):
        super().__init__(CartParams(**params))
        self.action, self.at, self.reads, self.writes, self.stopped = action, at, 0, [], 0

    def read(self):
        y = super().read()
        self.reads += 1
        if self.reads == self.at:
            y = self.action(y)
        return y

    def write(self, volts):
        self.writes.append(float(volts))
        super().write(volts)

    def stop(self):
        self.stopped += 1
        super().stop()


def _raise(exc):
    def action(y):
        raise exc

    return action


#: The clock of the real-time case, driven by the test (the machine's load decides nothing).
CLOCK = FakeClock()


def _late(y):
    CLOCK.stall(0.2)
    return y


CASES = {
    # name: (device action, limits, reference, clock, words in the fault)
    "track limit": (None, Limits(x_max=0.2), 0.3, "virtual", ["track limit", "0.2 m"]),
    "velocity limit": (None, Limits(speed_max=0.2), 0.5, "virtual", ["velocity limit", "0.2"]),
    "encoder jump": (lambda y: y + 0.02, Limits(), 0.3, "virtual", ["encoder jump", "0.02"]),
    "watchdog": (_late, Limits(late_max=0.05), 0.1, "perf_counter", ["watchdog", "200 ms late"]),
    "device error": (_raise(DeviceError("board gone")), Limits(), 0.3, "virtual", ["board gone"]),
    "ctrl-c": (_raise(KeyboardInterrupt()), Limits(), 0.3, "virtual", ["interrupted", "Ctrl-C"]),
}


@pytest.mark.parametrize("case", list(CASES), ids=list(CASES))
def test_fault_writes_zero_volts_and_records_why(tmp_path, case):
    action, limits, step, clock, words = CASES[case]
    device = Injected(action or (lambda y: y), at=100 if action else 10**9)
    result = run_loop(
        device,
        PID_LAB,
        np.full(2001, step),
        limits=limits,
        clock=clock,
        out=tmp_path / "f.toml",
        timer=CLOCK.timer,
    )
    assert result.status == "fault" and result.n_samples < 2001
    for word in words:
        assert word in result.fault, result.fault
    assert device.writes[-1] == 0.0 and device.last_voltage == 0.0 and device.stopped >= 1
    assert result.n_samples >= 2, result.fault  # the fault came at read 100, not before
    if case in ("track limit", "velocity limit", "watchdog"):  # a measured faulting sample
        assert result.command[-1] == 0.0
    if case == "encoder jump":  # a glitch is not data: the recording ends the sample before
        assert abs(result.position[-1] - result.position[-2]) < 0.005
    rec = read_experiment(result.path)
    assert rec.meta["run"]["status"] == "fault" and rec.meta["run"]["fault"] == result.fault
    assert rec.meta["run"]["last_voltage"] == 0.0
    assert rec.n_samples == result.n_samples
    np.testing.assert_array_equal(rec.command, result.command)
    assert "\n" not in result.fault


def test_nan_from_the_controller_is_a_fault():
    """A controller whose arithmetic gives nan (PID(...) refuses a nan gain, so the nan
    comes in through the reference) stops the loop at 0 V."""
    device = Injected(lambda y: y, at=10**9)
    reference = [float("nan")] * 50
    result = run_loop(device, PID(kp=1.0, v_limit=6.0), reference, clock="virtual")
    assert result.status == "fault" and "nan" in result.fault
    assert set(device.writes) == {0.0}  # nothing but the 0 V of the finally (and of stop)


def test_clamp_holds_the_voltage_within_v_max():
    result = run_loop(SimCart(), PID(kp=200.0, v_limit=6.0), [0.3] * 500, clock="virtual")
    assert np.abs(result.command).max() == 6.0


def test_unexpected_exception_is_recorded_then_raised(tmp_path):
    device = Injected(_raise(RuntimeError("bug in a device")), at=50)
    with pytest.raises(RuntimeError, match="bug in a device"):
        run_loop(device, PID_LAB, [0.3] * 500, clock="virtual", out=tmp_path / "x.toml")
    assert device.writes[-1] == 0.0 and device.stopped >= 1
    rec = read_experiment(tmp_path / "x.toml")
    assert rec.meta["run"]["fault"] == "error: RuntimeError: bug in a device (at t = 0.049 s)"


def test_a_crash_loses_at_most_the_last_flush(tmp_path):
    """While the run goes on, the files on disk already read, up to the last flush."""
    seen = {}

    def look(y):
        rec = read_experiment(tmp_path / "live.toml")
        seen["rows"], seen["status"] = rec.n_samples, rec.meta["run"]["status"]
        return y

    device = Injected(look, at=351)
    run_loop(device, PID_LAB, [0.3] * 500, clock="virtual", out=tmp_path / "live", flush_every=100)
    assert seen == {"rows": 300, "status": "running"}
    assert read_experiment(tmp_path / "live.toml").n_samples == 500


def test_never_over_an_existing_recording(tmp_path):
    from hw.expfile import ExpFileError

    run_loop(SimCart(), PID_LAB, [0.1] * 20, clock="virtual", out=tmp_path / "a.toml")
    before = (tmp_path / "a.csv").read_text()
    (tmp_path / "b.csv").write_text("mine\n")
    for name in ("a.toml", "b.toml"):
        with pytest.raises(ExpFileError, match="exists"):
            run_loop(SimCart(), PID_LAB, [0.1] * 20, clock="virtual", out=tmp_path / name)
    assert (tmp_path / "a.csv").read_text() == before
    assert (tmp_path / "b.csv").read_text() == "mine\n" and not (tmp_path / "b.toml").exists()


def test_the_csv_is_synced_to_the_disk_beside_the_loop(tmp_path):
    """A power loss loses at most the rows after the last fsync: a thread beside the loop
    fsyncs the CSV every sync_every [s] while the run goes on. The loop waits at read 100 until
    that thread has synced three times (its period is the machine's to keep: not asserted)."""
    import threading

    from hw.recorder import OsFiles

    synced = threading.Event()

    class Counting(OsFiles):
        def __init__(self):
            self.syncs = []

        def fsync(self, fd):
            super().fsync(fd)
            self.syncs.append(threading.current_thread().name)
            if sum(name != threading.main_thread().name for name in self.syncs) >= 3:
                synced.set()

    class Waiting(SimCart):
        reads = 0

        def read(self):
            self.reads += 1
            if self.reads == 100:
                assert synced.wait(600), "the recorder's fsync thread never synced"
            return super().read()

    files = Counting()
    result = run_loop(
        Waiting(),
        PID_LAB,
        np.full(301, 0.1),
        clock="virtual",
        out=tmp_path / "sync.toml",
        sync_every=0.01,
        files=files,
    )
    assert result.status == "completed", result.fault
    beside = [name for name in files.syncs if name != threading.main_thread().name]
    assert len(beside) >= 3 and read_experiment(result.path).n_samples == 301


def test_a_run_that_never_started_leaves_the_name_free(tmp_path):
    """A device that cannot start: no file left, and the retry with the same name runs."""
    out = tmp_path / "retry.toml"
    failed = run_loop(
        Injected(_raise(DeviceError("no board")), at=1),
        PID_LAB,
        [0.1] * 50,
        clock="virtual",
        out=out,
    )
    assert failed.status == "fault" and failed.path is None
    assert not out.exists() and not out.with_suffix(".csv").exists()
    assert "free for the retry" in failed.notes[-1]
    again = run_loop(SimCart(), PID_LAB, [0.1] * 50, clock="virtual", out=out)
    assert again.status == "completed" and read_experiment(out).n_samples == 50
