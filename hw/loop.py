"""The hardware loop: every sample, read the encoder, run the canonical PID, check, write, log.

    deadline k Ts --> read y_k --> [safety: nan, jump, track, speed] --> PID (hw/control_law.py)
         ^                                                              |
         |        log t, y, v, r, e, t_wall, compute <-- write u_k <-- [clamp v_max]
         '---------------------------- next sample ---------------------'
    every way out (the end, a fault, a device error, an exception, a full disk, Ctrl-C,
    SIGTERM, SIGHUP) goes through one finally: write 0 V, stop the device; then the recording
    is finished with the timing statistics and the reason the run ended

Signals: while the loop runs, SIGINT, SIGTERM and SIGHUP (SIGBREAK on Windows) raise into it,
once: a second Ctrl-C, or any signal while 0 V is written and the recording closed, is counted
in the reason and does not interrupt the stop (:class:`_Signals`). A signal that lands while the
recorder writes a chunk of the CSV waits for the chunk's end, so no line is cut.

Pacing (``clock``):
    "device"        the device's own clock: read() blocks until the next sample (a Quanser board's
                    hardware-timed encoder task); the loop only measures
    "perf_counter"  absolute deadlines t0 + k Ts on the computer's clock (time.perf_counter,
                    or the ``timer`` given: :class:`hw.pacing.Timer`): sleep until shortly
                    before, then spin the last stretch (no drift: a late sample does not move the
                    next deadline)
    "virtual"       no waiting: as fast as the machine allows, timestamps k Ts (simulated or
                    replayed devices only; for tests and quick runs)
In real time, ``gc.freeze()`` moves what exists to the permanent generation before the loop,
and the cyclic collector is off during the run (the loop allocates no cycles; reference
counting frees its floats), so that no collection pauses a sample.

>>> from hw.control_law import PID
>>> from hw.devices.sim import SimCart
>>> res = run_loop(SimCart(), PID(kp=50.0, v_limit=6.0), [0.1] * 1001, clock="virtual")
>>> res.status, round(float(res.position[-1]), 4)
('completed', 0.0997)
"""

from __future__ import annotations

import datetime as _dt
import gc
import math
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hw import pacing
from hw.control_law import PID, Floats, PIDState, float_clip, float_pid, pid_init, pid_stepper
from hw.devices.base import DeviceError
from hw.pacing import SPIN, Timer, timing_stats, wait_until
from hw.recorder import MIN_SAMPLES, RecorderError, RunRecorder
from hw.safety import Fault, Guard, Limits

CLOCKS = ("device", "perf_counter", "virtual")
#: What each stopping signal means to the person at the lab PC.
SIGNAL_REASONS = {
    "SIGINT": "interrupted (Ctrl-C)",
    "SIGTERM": "stopped by SIGTERM (a kill, a session manager or a CI timeout)",
    "SIGHUP": "stopped by SIGHUP (the terminal was closed)",
    "SIGBREAK": "stopped by Ctrl-Break (or the console was closed)",
}

__all__ = ["CLOCKS", "RunResult", "check_controller", "run_loop", "timing_stats"]


@dataclass(frozen=True, eq=False)
class RunResult:
    """What a run did (numpy float64 arrays, one entry per logged sample).

    status: "completed" | "fault"; fault: the reason the run stopped early (one line), or None
    time: k Ts [s]; position: y_k read [m]; command: u_k written [V] (0 at a faulting sample);
    reference: r_k [m]; t_wall: when y_k was read [s from the first sample]; compute: read to
    write [s]; timing: the statistics recorded in [timing]; path: the recording (TOML), or None
    (none asked, or the run never started and its files were removed); device: the device's
    description; signals: the stopping signals received ("SIGINT", ...), in order; notes: what
    could not be written to the recording itself (one line each); zero_failure: why no write
    of 0 V reached the device at the end (None: one did), when the output may still hold
    ``last_voltage``, the last voltage the device took [V] (nan: not known)
    """

    status: str
    fault: str | None
    time: np.ndarray
    position: np.ndarray
    command: np.ndarray
    reference: np.ndarray
    t_wall: np.ndarray
    compute: np.ndarray
    timing: dict
    path: Path | None
    device: dict
    signals: tuple = ()
    notes: tuple = ()
    zero_failure: str | None = None
    last_voltage: float = 0.0

    @property
    def zero_written(self) -> bool:
        """0 V reached the device at the end."""
        return self.zero_failure is None

    @property
    def n_samples(self) -> int:
        return int(self.position.shape[0])


class StopSignal(BaseException):
    """A stopping signal raised into the loop (a BaseException: nothing may swallow it)."""

    def __init__(self, name: str):
        super().__init__(name)
        self.name = name


class _Signals:
    """Handlers of the stopping signals for one run: the first raises :class:`StopSignal` into
    the loop (only when the loop's own frames are running, never while it stops); every one is
    counted. Installed only in the main thread (the only one Python delivers signals to)."""

    def __init__(self, enabled: bool):
        self.received: list[str] = []
        self.raised = False
        self.pending: str | None = None
        self._old: dict = {}
        self.enabled = enabled and threading.current_thread() is threading.main_thread()

    def __enter__(self):
        if self.enabled:
            for name in SIGNAL_REASONS:
                signum = getattr(signal, name, None)
                if signum is not None:
                    try:
                        self._old[signum] = signal.signal(signum, self._handler)
                    except (OSError, ValueError):  # not settable here
                        pass
        return self

    def __exit__(self, *exc):
        for signum, old in self._old.items():
            try:
                signal.signal(signum, old if old is not None else signal.SIG_DFL)
            except (OSError, ValueError):
                pass
        self._old = {}
        return False

    def _handler(self, signum, frame):
        name = signal.Signals(signum).name
        self.received.append(name)
        if self.raised or self.pending is not None:
            return
        if _raisable(frame):
            self.raised = True
            raise StopSignal(name)
        self.pending = name  # the loop raises it at its next sample, if it still runs

    def check(self) -> None:
        """Raise a signal that arrived outside the loop's frames (called every sample)."""
        if self.pending is not None and not self.raised:
            self.raised = True
            raise StopSignal(self.pending)


def _raisable(frame) -> bool:
    """True when ``frame`` runs inside the loop (``_drive``) and outside a critical section."""
    while frame is not None:
        code = frame.f_code
        if code in _CRITICAL:
            return False
        if code is _drive.__code__:
            return True
        frame = frame.f_back
    return False


def check_controller(pid: PID, limits: Limits) -> None:
    """Refuse a controller the loop cannot run as tuned (ValueError saying what to change)."""
    if not pid.v_limit <= limits.v_max:
        raise ValueError(
            f"the gains' software limit v_limit = {pid.v_limit:g} V exceeds the safety clamp "
            f"v_max = {limits.v_max:g} V, so the loop would not run the controller that was "
            f"tuned; tune with v_limit <= {limits.v_max:g} V (jaxcart tune --v-limit) or raise "
            "--v-max if the amplifier allows it"
        )
    if pid.sample_time < 1e-4:
        raise ValueError(
            f"sample_time = {pid.sample_time:g} s: the loop runs at most 10 kHz; tune for a "
            "sample time of 0.1 ms or more (the lab runs 1 ms)"
        )


def _check_clock(device, clock: str | None) -> str:
    if clock is None:
        clock = "device" if device.hardware_timed else "perf_counter"
    if clock not in CLOCKS:
        raise ValueError(f"clock = {clock!r}: use one of {', '.join(CLOCKS)}")
    if clock == "device" and not device.hardware_timed:
        raise ValueError(f"device {device.name} has no clock of its own; use clock='perf_counter'")
    if clock == "virtual" and not device.virtual:
        raise ValueError(f"device {device.name} is real hardware: it cannot run in virtual time")
    if clock == "perf_counter" and device.hardware_timed:
        raise ValueError(f"device {device.name} paces the loop itself; use clock='device'")
    return clock


@dataclass
class _RunRecord:
    """What one run has done so far (the loop appends one row per sample read)."""

    ts: float
    clock: str
    timer: Timer
    rows: list = field(default_factory=list)  # [t, y, u, r, t_wall, compute]
    k: int = 0
    fault: str | None = None
    measured: bool = True  # the faulting sample's position is a measurement
    error: BaseException | None = None
    notes: list = field(default_factory=list)
    zero_failure: str | None = None  # why 0 V never reached the device (None: it did)
    last_voltage: float = 0.0  # what the device took last [V]

    def stop(self, reason: str, *, measured: bool = True, error=None) -> None:
        """The reason the run ends (the first one given stands; later ones become notes)."""
        if self.fault is None:
            self.fault, self.measured = reason, measured
            if error is not None:
                self.error = error
        else:
            self.notes.append(reason)


def run_loop(
    device,
    pid: PID,
    reference,
    *,
    limits: Limits | None = None,
    clock: str | None = None,
    out=None,
    description: str | None = None,
    notes: dict | None = None,
    flush_every: int = 100,
    sync_every: float = 1.0,
    files=None,
    signals: bool = True,
    timer: Timer | None = None,
) -> RunResult:
    """Run ``pid`` on ``device`` for ``len(reference)`` samples of r_k [m]; record to ``out``.

    device: a :class:`hw.devices.base.Device`; pid: :class:`hw.control_law.PID` (every
    setting as tuned: sample time, derivative form, filter, anti-windup, software limit);
    limits: :class:`hw.safety.Limits` (default: the handout's); clock: "device",
    "perf_counter" or "virtual" (default: the device's clock if it has one, else
    perf_counter); out: the recording's path (TOML; the CSV beside it), never overwritten, or
    None for no recording; notes: extra provenance for [notes]; flush_every [samples],
    sync_every [s], files: see :mod:`hw.recorder`; signals: handle SIGINT, SIGTERM, SIGHUP;
    timer: where the time is read and slept (:class:`hw.pacing.Timer`; default the computer's,
    :data:`hw.pacing.SYSTEM_TIMER`).

    A safety fault, a device error, a recording error or a stopping signal ends the run with
    ``status = "fault"`` and the reason; any other exception is recorded the same way and
    raised again (with the result as its ``run_result``). In every case 0 V is written and the
    device stopped before this returns; where the device itself fails so that no write of 0 V
    reaches it, the result says so (``zero_failure``, and ``last_voltage`` what it holds). A
    run that stops before its second sample leaves no recording (nothing to read; the name
    stays free for the retry).
    """
    limits = limits or Limits()
    check_controller(pid, limits)
    clock = _check_clock(device, clock)
    ref = [float(r) for r in np.asarray(reference, dtype=float).ravel()]
    if len(ref) < 2:
        raise ValueError(f"the reference has {len(ref)} sample(s); give at least 2 (duration > Ts)")
    run = _RunRecord(ts=float(pid.sample_time), clock=clock, timer=timer or pacing.SYSTEM_TIMER)
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    run_table = {"status": "running", "started": started, "clock": clock}
    safety = {f"limit_{k}": v for k, v in limits.to_dict().items()}
    with _Signals(signals) as stops:  # from here on a signal stops the run, never the stop
        recorder = None
        if out is not None:
            tables = {
                "device": {**device.describe(), "clock": clock},
                "run": {**run_table, **safety},
            }
            if notes:
                tables["notes"] = dict(notes)
            recorder = RunRecorder(
                out,
                pid,
                description=description,
                tables=tables,
                flush_every=flush_every,
                sync_every=sync_every,
                files=files,
            )
        gc_was_enabled = gc.isenabled()
        real_time = clock != "virtual"
        try:
            if real_time:  # no collection may pause a sample (virtual time: no need)
                gc.collect()
                gc.freeze()
                gc.disable()
            _drive(device, pid, ref, limits, recorder, stops, run)
        except BaseException as exc:  # every way out; classified, then the same finally
            _classify(exc, run)
        finally:
            _zero(device, run)
            if real_time:
                if gc_was_enabled:
                    gc.enable()
                gc.unfreeze()
        result = _finish(device, ref, recorder, run, stops, run_table)
    if run.error is not None:
        try:
            run.error.run_result = result
        except AttributeError:
            pass
        raise run.error
    return result


def _drive(device, pid, ref, limits, recorder, stops, run) -> None:
    """Start the device and run the samples (the only frames a signal raises into)."""
    stops.check()
    ts = run.ts
    law = float_pid(pid)
    control = pid_stepper(law, Floats, float_clip)
    guard = Guard(limits, ts)
    perf = run.timer.now
    virtual = run.clock == "virtual"
    paced = run.clock == "perf_counter"
    rows = run.rows
    device.start(ts)
    state = None
    t0 = perf() + (2 * SPIN if paced else 0.0)
    for k in range(len(ref)):
        run.k = k
        stops.check()
        kts = k * ts
        if paced:
            wait_until(t0 + kts, run.timer)
        y = float(device.read())
        t_read = perf()
        if k == 0 and not paced:
            t0 = t_read
        t_wall = kts if virtual else t_read - t0
        r = ref[k]
        row = [kts, y, 0.0, r, t_wall, 0.0]  # u = the 0 V of the finally, should this fault
        rows.append(row)  # one append: a signal never leaves half a row
        if not virtual:
            guard.check_late(k, t_wall - kts)
        guard.check_position(k, y)
        if state is None:
            s = pid_init(law, r, y, xp=np)
            state = PIDState(float(s.integral), float(s.derivative), float(s.previous))
        u, _, state = control(state, r, y)
        u = guard.clamp(u)
        device.write(u)
        row[2] = u
        row[5] = perf() - t_read
        if recorder is not None:
            recorder.row(*row)
    run.k = len(ref)


def _classify(exc: BaseException, run: _RunRecord) -> None:
    """The reason a run ended, from what ended it."""
    t = f"t = {run.k * run.ts:.3f} s"
    if isinstance(exc, Fault):
        run.stop(str(exc), measured=exc.measured)
    elif isinstance(exc, DeviceError):
        run.stop(f"device: {_line(exc)}")
    elif isinstance(exc, RecorderError):
        run.stop(f"{_line(exc)} (at {t})")
    elif isinstance(exc, StopSignal):
        run.stop(f"{SIGNAL_REASONS.get(exc.name, exc.name)} at {t}")
    elif isinstance(exc, KeyboardInterrupt):  # signals not handled here (another thread)
        run.stop(f"{SIGNAL_REASONS['SIGINT']} at {t}")
    else:
        run.stop(f"error: {type(exc).__name__}: {_line(exc)} (at {t})", error=exc)


def _line(exc) -> str:
    return " ".join(str(exc).split())


def _zero(device, run: _RunRecord) -> None:
    """0 V, then stop(): each runs whatever the other does (a signal does not raise here).
    Whether 0 V reached the device is judged by what it says it took last (``last_voltage``:
    a write that raises leaves it as it was), so that the run never claims a 0 V it did not
    write."""
    failure = None
    try:
        device.write(0.0)
    except BaseException as exc:  # noqa: BLE001 - stop() below writes 0 V again
        failure = _line(exc)
    try:
        device.stop()
    except BaseException as exc:  # noqa: BLE001 - the recording must still be closed
        run.notes.append(f"stopping the device failed: {_line(exc)}")
    try:
        run.last_voltage = float(device.last_voltage)
    except BaseException:  # noqa: BLE001 - not known: then 0 V is not claimed either
        run.last_voltage = math.nan
    if run.last_voltage == 0.0:
        if failure is not None:
            run.notes.append(f"the first write of 0 V failed ({failure}); stop() wrote it")
    else:
        run.zero_failure = failure or "the device did not take it"


def _finish(device, ref, recorder, run: _RunRecord, stops: _Signals, run_table: dict) -> RunResult:
    """The recording finished and the result built; every step runs whatever the others do."""
    rows = run.rows
    if rows and (not run.measured or not _finite(rows[-1][1])):
        rows.pop()  # the faulting read was not a position (nan, a glitch): not data
    if rows and run.zero_failure is not None and _finite(run.last_voltage):
        rows[-1][2] = run.last_voltage  # not the 0 V that never reached the device
    if recorder is not None and len(rows) > recorder.rows and recorder.error is None:
        try:  # the faulting sample: its position as read, the 0 V written
            recorder.row(*rows[-1])
        except BaseException as exc:  # noqa: BLE001
            run.stop(_line(exc))
    if recorder is not None and recorder.error is None:
        try:
            recorder.flush()
        except BaseException as exc:  # noqa: BLE001
            run.stop(_line(exc))
    virtual = run.clock == "virtual"
    t_wall = np.array([row[4] for row in rows], dtype=float)
    compute = np.array([row[5] for row in rows], dtype=float)
    try:
        timing = timing_stats(t_wall, compute, run.ts, virtual=virtual)
    except BaseException as exc:  # noqa: BLE001 - a summary must not lose the run
        timing = {"samples": len(rows), "error": _line(exc)}
        run.stop(f"error: {type(exc).__name__} in the timing summary: {_line(exc)}", error=exc)
    extra = len(stops.received) - (1 if stops.raised else 0)
    if stops.received and (extra > 0 or not stops.raised):
        names = ", ".join(stops.received[1 if stops.raised else 0 :])
        run.notes.append(f"signals while stopping (not interrupting it): {names}")
        if run.fault is None:
            run.stop(f"{SIGNAL_REASONS.get(stops.received[0], 'a signal')} as the run ended")
    device_table = _describe(device, run)
    path = None
    if recorder is not None:
        path = _close(recorder, run, run_table, timing, device_table, device)
    return RunResult(
        status="completed" if run.fault is None else "fault",
        fault=run.fault,
        time=np.array([row[0] for row in rows], dtype=float),
        position=np.array([row[1] for row in rows], dtype=float),
        command=np.array([row[2] for row in rows], dtype=float),
        reference=np.asarray(ref[: len(rows)], dtype=float),
        t_wall=t_wall,
        compute=compute,
        timing=timing,
        path=path,
        device=device_table,
        signals=tuple(stops.received),
        notes=tuple(run.notes),
        zero_failure=run.zero_failure,
        last_voltage=run.last_voltage,
    )


def _finite(y) -> bool:
    try:
        return math.isfinite(y)
    except TypeError:
        return False


def _describe(device, run: _RunRecord) -> dict:
    try:
        return {**device.describe(), "clock": run.clock}  # as started (e.g. the watchdog)
    except BaseException as exc:  # noqa: BLE001
        run.notes.append(f"describing the device failed: {_line(exc)}")
        return {"clock": run.clock}


def _close(recorder, run: _RunRecord, run_table, timing, device_table, device) -> Path | None:
    """The recording's end: [run], [timing], [device]; or, never started, no files at all."""
    if recorder.saved < MIN_SAMPLES:
        try:
            recorder.discard()
        except BaseException as exc:  # noqa: BLE001
            run.notes.append(f"removing the recording failed: {_line(exc)}")
        run.notes.append(
            f"no recording kept: the run stopped before {MIN_SAMPLES} samples were saved; "
            f"{recorder.path} is free for the retry"
        )
        if run.fault is None:
            run.stop("the recording holds fewer than 2 samples")
        return None
    timing = {k: v for k, v in timing.items() if isinstance(v, int | float | str)}
    for _ in range(2):  # once more if finishing raised: the TOML then names that error
        tables = {"run": _final(recorder, run, run_table, device), "timing": timing}
        tables["device"] = device_table
        try:
            path, notes = recorder.close(tables)
        except BaseException as exc:  # noqa: BLE001
            run.stop(
                f"error: {type(exc).__name__} finishing the recording: {_line(exc)}", error=exc
            )
            continue
        run.notes.extend(notes)
        return path
    run.notes.append(f"{recorder.path} could not be finished: it may still say running")
    recorder.close_files()
    return recorder.path


def _final(recorder, run: _RunRecord, run_table: dict, device) -> dict:
    """The recording's [run] table at the end: status, samples, the reason, the notes."""
    m = recorder.saved
    final = {**run_table, "status": "completed" if run.fault is None else "fault"}
    final.update(samples=m, duration=m * run.ts)
    if len(run.rows) != m:
        final["samples_read"] = len(run.rows)
    if run.fault is not None:
        final["fault"] = run.fault
    if run.notes:
        final["notes"] = "; ".join(run.notes)
    stop_errors = getattr(device, "stop_errors", None)
    if stop_errors:
        final["stop_errors"] = "; ".join(stop_errors)
    if _finite(run.last_voltage):
        final["last_voltage"] = run.last_voltage
    final["zero_written"] = run.zero_failure is None
    if run.zero_failure is not None:
        final["zero_failure"] = run.zero_failure
    return final


# Sections where a signal waits: a chunk of the CSV is written whole or cut back first.
_CRITICAL = frozenset(
    {RunRecorder.row.__code__, RunRecorder.flush.__code__, RunRecorder._write_all.__code__}
)
