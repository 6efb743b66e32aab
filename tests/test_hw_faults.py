"""Fault injection into `python -m hw run`: every fault a lab sees, at random points of a run.

Each fault runs RUNS times through the command (hw.cli.main, in this process), on a wrapper of
the simulated cart that logs every write and stop() and injects the fault: signals (once, many
times, in the loop, in stop(), in the timing summary, in the recorder's close), exceptions
anywhere (the device, the control law, the timing summary, the recorder), a full disk, a
read-only folder, device errors, nan and jumps from the encoder, stalls. Every run must end
with the last write 0 V, stop() called, a non-zero exit status, and either a recording that
jaxcart's own reader reads, whose [run] fault names the fault and holds no nan, or (a run
stopped before 2 samples were saved) no file at all, so that a retry finds the name free. A
file system that turns read-only is the documented limit: the CSV reads, the TOML cannot be
finished (it says running), the reason is printed.
Virtual time and 0.3 s runs keep it fast (stalls: real time on a clock the test drives, 0.08 s)."""

import errno
import math
import os
import signal
import zlib
from collections import Counter

import numpy as np
import pytest
from fakeclock import FakeClock

import hw.cli
import hw.loop
import hw.pacing
import hw.recorder
from hw.cli import main
from hw.control_law import PID
from hw.devices.base import DeviceError
from hw.devices.sim import CartParams, SimCart
from hw.gains import write_gains
from jaxcart.files import read_experiment

RUNS = 20
SAMPLES = 301  # --duration 0.3 at 1 ms
PID_LAB = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
#: Injected runs per fault, counted as they run (printed at the end of the module).
COUNTS: Counter = Counter()
OUTCOMES: Counter = Counter()


class Rig(SimCart):
    """The simulated cart, logging every write and stop(); ``hooks`` inject faults:
    read(k, y) -> y at read number k (from 0), write(k, volts), start(), stop()."""

    def __init__(self, **hooks):
        super().__init__(CartParams(f_c=0.2))
        self.hooks, self.reads, self.writes, self.stops = hooks, 0, [], 0

    def start(self, sample_time):
        if "start" in self.hooks:
            self.hooks["start"]()
        super().start(sample_time)

    def read(self):
        y = super().read()
        k, self.reads = self.reads, self.reads + 1
        return self.hooks["read"](k, y) if "read" in self.hooks else y

    def write(self, volts):
        self.writes.append(float(volts))
        if "write" in self.hooks:
            self.hooks["write"](self.reads - 1, volts)
        super().write(volts)

    def stop(self):
        self.stops += 1
        if "stop" in self.hooks:
            self.hooks["stop"]()
        super().stop()


class Disk(hw.recorder.OsFiles):
    """A disk with ``free`` bytes left: a write that grows a file past it writes what fits,
    then the next raises ENOSPC; overwriting a file in place needs no space."""

    def __init__(self, free):
        self.free = int(free)

    def write(self, fd, data):
        pos, size = os.lseek(fd, 0, os.SEEK_CUR), os.fstat(fd).st_size
        growth = max(0, pos + len(data) - size)
        if growth > self.free:
            fit = len(data) - (growth - self.free)
            if fit <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            data = data[:fit]
        n = os.write(fd, data)
        self.free -= max(0, pos + n - size)
        return n

    def truncate(self, fd, size):
        old = os.fstat(fd).st_size
        os.ftruncate(fd, size)
        self.free += max(0, old - size)


class ReadOnlyFolder(hw.recorder.OsFiles):
    """A folder that turns read-only after ``after`` file operations: no file can be created,
    renamed or removed in it (EACCES); files already open are still written (as under chmod)."""

    def __init__(self, after):
        self.after, self.ops = after, 0

    def _check(self):
        self.ops += 1
        if self.ops > self.after:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))

    def mkdir(self, path):
        self._check()
        super().mkdir(path)

    def create(self, path):
        self._check()
        return super().create(path)

    def replace(self, src, dst):
        self._check()
        super().replace(src, dst)

    def unlink(self, path):
        self._check()
        super().unlink(path)


class Hooked(hw.recorder.OsFiles):
    """Runs ``hook(name)`` before each file operation of the recorder (a signal, a raise)."""

    def __init__(self, hook):
        self.hook = hook

    def __getattribute__(self, name):
        attr = super().__getattribute__(name)
        if name in ("create", "write", "replace", "fsync", "truncate", "unlink", "seek"):
            hook = super().__getattribute__("hook")

            def wrapped(*args):
                hook(name)
                return attr(*args)

            return wrapped
        return attr


@pytest.fixture(scope="module", autouse=True)
def counts_table(request):
    """After the module: the injected runs per fault and how each ended (the closing note of
    issue 23 quotes this table; run with -s to see it)."""
    yield
    lines = ["", "injected runs per fault:"]
    for name, n in sorted(COUNTS.items()):
        outcomes = ", ".join(f"{o} {c}" for (f, o), c in OUTCOMES.items() if f == name)
        lines.append(f"  {name:36s} {n:3d}  ({outcomes})")
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    for line in lines:
        reporter.write_line(line) if reporter else print(line)


@pytest.fixture(scope="module")
def gains(tmp_path_factory):
    return str(write_gains(tmp_path_factory.mktemp("g") / "gains.json", PID_LAB, note="faults"))


def _signal_to_self(name):
    signal.raise_signal(getattr(signal, name))


def _run(monkeypatch, tmp_path, gains, rig, *, files=None, extra=(), i=0):
    """One run of the command; returns (exit status, TOML path, stderr lines)."""
    monkeypatch.setattr(hw.cli, "make_device", lambda args: rig)
    if files is not None:
        monkeypatch.setattr(hw.recorder, "OsFiles", lambda: files)
    out = tmp_path / f"run{i}.toml"
    argv = ["run", gains, "--device", "sim", "--step", "0.3", "--duration", "0.3", "--out"]
    status = main(argv + [str(out), *extra])
    monkeypatch.undo()
    return status, out


def out_of(tmp_path, i, suffix=".toml"):
    return tmp_path / f"run{i}{suffix}"


def _promises(name, rig, status, out, words, capsys, *, exit_status=None):
    """The promises of issue 23 item 1 for one run (see the module docstring)."""
    err = capsys.readouterr().err
    COUNTS[name] += 1
    assert rig.writes and rig.writes[-1] == 0.0, (name, rig.writes[-3:])
    assert rig.stops >= 1, name
    assert status != 0, (name, err)
    if exit_status is not None:
        assert status == exit_status, (name, status, err)
    csv = out.with_suffix(".csv")
    if not out.exists():  # stopped before 2 samples were saved: nothing blocks the retry
        assert not csv.exists() and not list(out.parent.glob(f".{out.name}*")), name
        assert any(w in err for w in words), (name, err)
        OUTCOMES[name, "no recording (stopped before 2 samples)"] += 1
        return None
    rec = read_experiment(out)
    run = rec.meta["run"]
    assert run["status"] == "fault", (name, run)
    assert any(w in run["fault"] for w in words), (name, run["fault"])
    assert np.all(np.isfinite(rec.position)) and np.all(np.isfinite(rec.command)), name
    assert rec.n_samples == run["samples"] >= 2, name
    assert not list(out.parent.glob(f".{out.name}*")), name  # no temporary file left
    OUTCOMES[name, "recording"] += 1
    return rec


def _rng(name):
    return np.random.default_rng(zlib.crc32(name.encode()))


# ---------------------------------------------------------------- signals


@pytest.mark.parametrize(
    "sig, words, code",
    [
        ("SIGINT", ["Ctrl-C"], 130),
        ("SIGTERM", ["SIGTERM"], 143),
        ("SIGHUP", ["SIGHUP"], 129),
    ],
)
def test_a_signal_at_a_random_sample(monkeypatch, tmp_path, gains, capsys, sig, words, code):
    for i, at in enumerate(_rng(sig).integers(0, SAMPLES, RUNS)):

        def read(k, y, at=at):
            if k == at:
                _signal_to_self(sig)
            return y

        rig = Rig(read=read)
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        _promises(f"{sig} once", rig, status, out, words, capsys, exit_status=code)


def test_ctrl_c_many_times_anywhere(monkeypatch, tmp_path, gains, capsys):
    """Ctrl-C at a random sample, then again in stop(), in the timing summary and while the
    recording closes (each with probability 1/2): the first stops the run, the others are
    counted and never interrupt the stop."""
    rng = _rng("many")
    real_stats = hw.loop.timing_stats
    for i in range(RUNS):
        at = int(rng.integers(0, SAMPLES))
        where = {w for w in ("stop", "timing", "close") if rng.random() < 0.5}

        def read(k, y, at=at):
            if k == at:
                _signal_to_self("SIGINT")
            return y

        rig = Rig()

        def stats(*args, where=where, rig=rig, **kw):
            if "timing" in where and rig.reads:  # the run's summary, not the pre-run check's
                _signal_to_self("SIGINT")
                _signal_to_self("SIGINT")
            return real_stats(*args, **kw)

        def file_hook(op, where=where):
            if "close" in where and op in ("replace", "fsync"):
                _signal_to_self("SIGINT")

        rig.hooks["read"] = read
        if "stop" in where:
            rig.hooks["stop"] = lambda: _signal_to_self("SIGINT")
        monkeypatch.setattr(hw.loop, "timing_stats", stats)
        status, out = _run(monkeypatch, tmp_path, gains, rig, files=Hooked(file_hook), i=i)
        rec = _promises("SIGINT many times", rig, status, out, ["Ctrl-C"], capsys, exit_status=130)
        if rec is not None and where & {"stop", "timing"}:  # those before the TOML's end
            assert "signals while stopping" in rec.meta["run"]["notes"]


def test_a_signal_only_while_stopping_still_finishes(monkeypatch, tmp_path, gains, capsys):
    """A run that completes, then a signal in stop(): 0 V, the recording finished with every
    sample, the signal named, exit 128 + its number."""
    names = _rng("stopping").choice(["SIGINT", "SIGTERM", "SIGHUP"], RUNS)
    for i, sig in enumerate(names):
        rig = Rig(stop=lambda sig=sig: _signal_to_self(sig))
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        words = [{"SIGINT": "Ctrl-C"}.get(sig, sig)]
        code = 128 + int(getattr(signal, sig))
        rec = _promises(
            "a signal only in stop()", rig, status, out, words, capsys, exit_status=code
        )
        assert rec.n_samples == SAMPLES and "as the run ended" in rec.meta["run"]["fault"]


# ---------------------------------------------------------------- exceptions


def _raise_at(at, exc):
    def hook(k, *rest):
        if k == at:
            raise exc
        return rest[0] if rest else None

    return hook


@pytest.mark.parametrize("where", ["read", "write"])
def test_an_exception_in_the_device(monkeypatch, tmp_path, gains, capsys, where):
    for i, at in enumerate(_rng(where).integers(0, SAMPLES, RUNS)):
        rig = Rig(**{where: _raise_at(at, RuntimeError(f"bug in {where}"))})
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        _promises(f"exception in {where}()", rig, status, out, [f"bug in {where}"], capsys)


def test_an_exception_in_the_control_law(monkeypatch, tmp_path, gains, capsys):
    real = hw.loop.pid_stepper
    for i, at in enumerate(_rng("law").integers(0, SAMPLES, RUNS)):
        rig = Rig()

        def stepper(*args, at=at, rig=rig, **kw):
            step = real(*args, **kw)

            def law(*args):
                if rig.reads == at + 1:  # the run's law, not the pre-run check's
                    raise ZeroDivisionError("bug in the law")
                return step(*args)

            return law

        monkeypatch.setattr(hw.loop, "pid_stepper", stepper)
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        _promises("exception in the control law", rig, status, out, ["bug in the law"], capsys)


def test_an_exception_in_the_timing_summary(monkeypatch, tmp_path, gains, capsys):
    rng = _rng("timing")
    real_stats = hw.loop.timing_stats
    for i in range(RUNS):
        at = int(rng.integers(0, 2 * SAMPLES))  # half the runs also fault at a random sample

        def read(k, y, at=at):
            return y + 0.05 if k == at else y  # an encoder jump

        rig = Rig(read=read)

        def stats(*args, rig=rig, **kw):
            if rig.reads:  # the run's summary, not the pre-run check's
                raise ValueError("bug in the summary")
            return real_stats(*args, **kw)

        monkeypatch.setattr(hw.loop, "timing_stats", stats)
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        words = ["bug in the summary", "encoder jump"]
        rec = _promises("exception in the timing summary", rig, status, out, words, capsys)
        if rec is not None:
            assert rec.meta["timing"]["error"] == "bug in the summary"


def test_an_exception_in_the_recorder(monkeypatch, tmp_path, gains, capsys):
    """The recorder's file operations raise at a random one (a bug, not a disk error)."""
    rng = _rng("recorder")
    for i in range(RUNS):
        at = int(rng.integers(1, 12))
        count = [0]

        def hook(op, at=at, count=count):
            count[0] += 1
            if count[0] == at:
                raise RuntimeError(f"bug in the recorder ({op})")

        rig = Rig()
        if at <= 3:  # while the files are created, before the start: the bug is raised
            with pytest.raises(RuntimeError, match="bug in the recorder"):
                _run(monkeypatch, tmp_path, gains, rig, files=Hooked(hook), i=i)
            monkeypatch.undo()
            COUNTS["exception in the recorder"] += 1
            OUTCOMES["exception in the recorder", "raised before the start"] += 1
            assert not out_of(tmp_path, i).exists() and not out_of(tmp_path, i, ".csv").exists()
            assert rig.writes == [] and rig.stops == 0
            continue
        status, out = _run(monkeypatch, tmp_path, gains, rig, files=Hooked(hook), i=i)
        words = ["bug in the recorder", "RuntimeError"]
        _promises("exception in the recorder", rig, status, out, words, capsys)


# ---------------------------------------------------------------- disks


def test_a_full_disk_at_a_random_byte(monkeypatch, tmp_path, gains, capsys):
    """The disk fills at a random byte (the whole run needs ~30 kB: the TOML with its kept
    space 5 kB, the CSV 24 kB, the final TOML's temporary copy 1 kB): the CSV keeps every whole
    line that fits, the run stops at 0 V, and the TOML is finished in the space kept for it."""
    rng = _rng("disk")
    for i in range(RUNS):
        free = int(rng.integers(4000, 29000))
        rig = Rig()
        status, out = _run(monkeypatch, tmp_path, gains, rig, files=Disk(free), i=i)
        err = capsys.readouterr().err
        if status == 2:  # full before the files were created: refused, nothing left
            COUNTS["full disk"] += 1
            OUTCOMES["full disk", "refused before the start"] += 1
            assert "disk is full" in err and not out.exists()
            assert not out.with_suffix(".csv").exists() and rig.writes == []
            continue
        if status == 0:  # every row fitted; only the TOML's temporary copy did not
            COUNTS["full disk"] += 1
            OUTCOMES["full disk", "complete, TOML finished in place"] += 1
            rec = read_experiment(out)
            assert rec.n_samples == SAMPLES and rec.meta["run"]["status"] == "completed"
            assert "finished in place (the disk is full)" in err and rig.writes[-1] == 0.0
            continue
        rec = _promises("full disk", rig, status, out, ["disk is full"], _Err(err))
        if rec is not None:
            lines = out.with_suffix(".csv").read_text().splitlines()
            assert all(line.count(",") == 6 for line in lines)  # no line cut


class _Err:
    """capsys stand-in for stderr already read."""

    def __init__(self, err):
        self.err = err

    def readouterr(self):
        return self


def test_a_read_only_folder(monkeypatch, tmp_path, gains, capsys):
    """Read-only from the start: one line, exit 2, nothing left. Turning read-only during the
    run (no file can be created or renamed; open files are still written): the run completes
    and the TOML is finished in place, with a note."""
    rng = _rng("read-only")
    for i in range(RUNS):
        # 0: the folder cannot be made; 1: no file in it; 3: no temporary file at the end;
        # 4: no rename (between 1 and 3 the CSV could be neither kept nor removed).
        after = int(rng.choice([0, 1, 3, 4]))
        rig = Rig()
        folder = tmp_path / f"ro{i}"
        monkeypatch.setattr(hw.cli, "make_device", lambda args, rig=rig: rig)
        monkeypatch.setattr(hw.recorder, "OsFiles", lambda after=after: ReadOnlyFolder(after))
        out = folder / "run.toml"
        argv = ["run", gains, "--step", "0.3", "--duration", "0.3", "--out", str(out)]
        status = main(argv)
        monkeypatch.undo()
        err = capsys.readouterr().err
        COUNTS["read-only folder"] += 1
        if after < 2:  # the folder or a file of the recording could not be created
            OUTCOMES["read-only folder", "refused before the start"] += 1
            assert status == 2 and "read-only" in err and err.count("\n") >= 1
            assert not out.exists() and not out.with_suffix(".csv").exists()
            assert rig.writes == [] and rig.stops == 0  # nothing was started
            continue
        OUTCOMES["read-only folder", "recording finished in place"] += 1
        rec = read_experiment(out)
        assert rec.n_samples == SAMPLES and rig.writes[-1] == 0.0 and rig.stops >= 1
        assert rec.meta["run"]["status"] == "completed" and "timing" in rec.meta
        assert status == 0 and "finished in place" in err
        # The temporary file can be neither renamed nor removed in a read-only folder; it is
        # hidden and blocks nothing.
        assert len(list(folder.glob(".run.toml*"))) == (after == 4)


class ReadOnlyFileSystem(hw.recorder.OsFiles):
    """A file system that turns read-only (EROFS on every operation) after ``after`` writes
    of the CSV's chunks: a USB stick pulled out, an error remount."""

    def __init__(self, after):
        self.after, self.ops = after, 0

    def _check(self):
        if self.ops >= self.after:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    def write(self, fd, data):
        self._check()
        self.ops += 1
        return super().write(fd, data)

    def create(self, path):
        self._check()
        return super().create(path)

    def replace(self, src, dst):
        self._check()
        super().replace(src, dst)

    def truncate(self, fd, size):
        self._check()
        super().truncate(fd, size)

    def fsync(self, fd):
        self._check()
        super().fsync(fd)


def test_a_file_system_that_turns_read_only(monkeypatch, tmp_path, gains, capsys):
    """The documented limit: nothing more can be written, so the TOML still says running; the
    CSV keeps its whole lines and reads, the run stops at 0 V and the reason is printed."""
    rng = _rng("erofs")
    for i in range(RUNS):
        after = int(rng.integers(3, 6))  # the header and the TOML, then 1-3 chunks of 100
        rig = Rig()
        status, out = _run(monkeypatch, tmp_path, gains, rig, files=ReadOnlyFileSystem(after), i=i)
        err = capsys.readouterr().err
        COUNTS["file system turns read-only"] += 1
        assert rig.writes[-1] == 0.0 and rig.stops >= 1 and status == 1
        assert "the file system is read-only" in err and "still says running" in err
        OUTCOMES["file system turns read-only", "CSV reads, TOML running"] += 1
        rec = read_experiment(out)
        assert rec.meta["run"]["status"] == "running" and rec.n_samples == 100 * (after - 2)


# ---------------------------------------------------------------- the device


@pytest.mark.parametrize("where", ["read", "write", "start"])
def test_a_device_error(monkeypatch, tmp_path, gains, capsys, where):
    rng = _rng(f"device {where}")
    for i in range(RUNS):
        at = int(rng.integers(0, SAMPLES))
        exc = DeviceError(f"board lost ({where})")
        if where == "start":

            def start(exc=exc):
                raise exc

            rig = Rig(start=start)
        else:
            rig = Rig(**{where: _raise_at(at, exc)})
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        rec = _promises(f"device error in {where}()", rig, status, out, ["board lost"], capsys)
        assert status == 1
        if where == "start":
            assert rec is None  # never started: nothing left


def test_a_device_whose_stop_fails(monkeypatch, tmp_path, gains, capsys):
    for i, at in enumerate(_rng("stop").integers(0, SAMPLES, RUNS)):

        def stop():
            raise DeviceError("stop failed")

        rig = Rig(read=_raise_at(at, DeviceError("board lost")), stop=stop)
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        rec = _promises("device error, then stop() fails", rig, status, out, ["board lost"], capsys)
        if rec is not None:
            assert "stop failed" in rec.meta["run"]["notes"]


@pytest.mark.parametrize("lasting", [True, False])
def test_a_device_that_disconnects_is_not_said_to_be_at_0_volts(
    monkeypatch, tmp_path, gains, capsys, lasting
):
    """A USB cable pulled at sample 150: every write from there on raises, the 0 V of the
    stop too. The last line says 0 V was not written and what the output may still hold, the
    last voltage the device took, which is the recording's last voltage. A write that failed
    once (not lasting) is followed by a 0 V that reached it, and the last line says that."""

    failed = []

    def write(k, volts):
        if k >= 150 and (lasting or not failed):
            failed.append(k)
            raise DeviceError("USB: device disconnected")

    rig = Rig(write=write)
    status, out = _run(monkeypatch, tmp_path, gains, rig)
    lines = capsys.readouterr().err.strip().splitlines()
    rec = _promises("device disconnected", rig, status, out, ["disconnected"], capsys)
    assert status == 1
    run = rec.meta["run"]
    assert lines[-1].startswith("hw run: stopped: device: USB: device disconnected; ")
    if lasting:
        held = rig.last_voltage
        assert held != 0.0 and run["zero_written"] is False and run["last_voltage"] == held
        assert rec.command[-1] == held and rec.command[-2] == held  # 149 held, 150 not taken
        assert run["zero_failure"] == "USB: device disconnected"
        assert lines[-1].endswith(
            f"writing 0 V FAILED (USB: device disconnected): the output may still hold "
            f"{held:.4g} V, the last voltage it took; switch the amplifier off"
        )
        assert not any("0 V written" in line for line in lines)
    else:
        assert rig.last_voltage == 0.0 and run["zero_written"] is True
        assert rec.command[-1] == 0.0 and "zero_failure" not in run
        assert lines[-1].endswith("; 0 V written and the device stopped")


@pytest.mark.parametrize("value", ["nan", "inf", "jump"])
def test_the_encoder_reads_nonsense(monkeypatch, tmp_path, gains, capsys, value):
    rng = _rng(f"encoder {value}")
    for i in range(RUNS):
        at = int(rng.integers(1, SAMPLES))  # a glitch at the first read is the start position
        jump = float(rng.choice([-1, 1]) * 10 ** rng.uniform(-2, 5))  # 1 cm .. 100 km

        def read(k, y, at=at, jump=jump):
            if k != at:
                return y
            return {"nan": math.nan, "inf": math.inf, "jump": y + jump}[value]

        rig = Rig(read=read)
        status, out = _run(monkeypatch, tmp_path, gains, rig, i=i)
        words = ["encoder jump"] if value == "jump" else [f"read {value}"]
        rec = _promises(f"encoder {value}", rig, status, out, words, capsys)
        assert status == 1
        if rec is not None:  # the faulting read is named in the reason, not recorded as data
            assert rec.n_samples == at


def test_a_stall_stops_on_the_watchdog(monkeypatch, tmp_path, gains, capsys):
    """The device stalls 30 ms at a random sample of a real-time run (watchdog 10 ms), on a
    clock the test drives (the machine's own load would stop runs at other samples)."""
    rng = _rng("stall")
    for i in range(RUNS):
        at = int(rng.integers(0, 60))
        clock = FakeClock()

        def read(k, y, at=at, clock=clock):
            if k == at:
                clock.stall(0.03)
            return y

        rig = Rig(read=read)
        monkeypatch.setattr(hw.pacing, "SYSTEM_TIMER", clock.timer)
        monkeypatch.setattr(hw.cli, "make_device", lambda args, rig=rig: rig)
        out = tmp_path / f"stall{i}.toml"
        argv = ["run", gains, "--duration", "0.08", "--real-time", "--watchdog", "0.01"]
        status = main(argv + ["--out", str(out)])
        monkeypatch.undo()
        rec = _promises("stall", rig, status, out, ["watchdog"], capsys, exit_status=1)
        if rec is not None:  # stopped on the stalled sample itself, no other
            assert f"watchdog: sample {at} " in rec.meta["run"]["fault"]
            assert "was read 30 ms late" in rec.meta["run"]["fault"]
