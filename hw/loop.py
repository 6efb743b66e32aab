"""The hardware loop: every sample, read the encoder, run the canonical PID, check, write, log.

    deadline k Ts --> read y_k --> [safety: track, jump, speed] --> PID (hw/control_law.py)
         ^                                                              |
         |        log t, y, v, r, e, t_wall, compute <-- write u_k <-- [clamp v_max]
         '---------------------------- next sample ---------------------'
    finally (normal end, fault, exception or Ctrl-C): write 0 V, stop the device, close the
    recording with the timing statistics and the reason the run ended

Pacing (``clock``):
    "device"        the device's own clock: read() blocks until the next sample (a Quanser board's
                    hardware-timed encoder task); the loop only measures
    "perf_counter"  absolute deadlines t0 + k Ts on time.perf_counter: sleep until shortly
                    before, then spin the last stretch (no drift: a late sample does not move the
                    next deadline)
    "virtual"       no waiting: as fast as the machine allows, timestamps k Ts (simulated or
                    replayed devices only; for tests and quick runs)
``gc.freeze()`` moves what exists to the permanent generation before the loop, and the cyclic
collector is off during a real-time run (the loop allocates no cycles; reference counting frees
its floats), so that no collection pauses a sample.

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
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hw.control_law import PID, PIDState, float_pid, pid_init, pid_update
from hw.devices.base import DeviceError
from hw.recorder import RunRecorder
from hw.safety import Fault, Guard, Limits

CLOCKS = ("device", "perf_counter", "virtual")
#: The last stretch before a deadline is spun, not slept (sleep overshoots by ~50-100 us).
SPIN = 300e-6


class _Floats:
    """The array namespace of the control law on Python floats (numpy scalars are ~10x slower):
    the same arithmetic, so the same numbers."""

    abs = staticmethod(abs)

    @staticmethod
    def where(condition, a, b):
        return a if condition else b


def _clip(v, limit):
    return min(max(v, -limit), limit)


@dataclass(frozen=True, eq=False)
class RunResult:
    """What a run did (numpy float64 arrays, one entry per logged sample).

    status: "completed" | "fault"; fault: the reason the run stopped early (one line), or None
    time: k Ts [s]; position: y_k read [m]; command: u_k written [V] (0 at a faulting sample);
    reference: r_k [m]; t_wall: when y_k was read [s from the first sample]; compute: read to
    write [s]; timing: the statistics recorded in [timing]; path: the recording (TOML) or None;
    device: the device's description
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

    @property
    def n_samples(self) -> int:
        return int(self.position.shape[0])


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
) -> RunResult:
    """Run ``pid`` on ``device`` for ``len(reference)`` samples of r_k [m]; record to ``out``.

    device: a :class:`hw.devices.base.Device`; pid: :class:`hw.control_law.PID` (every
    setting as tuned: sample time, derivative form, filter, anti-windup, software limit);
    limits: :class:`hw.safety.Limits` (default: the handout's); clock: "device",
    "perf_counter" or "virtual" (default: the device's clock if it has one, else
    perf_counter); out: the recording's path (TOML; the CSV beside it), never overwritten, or
    None for no recording; notes: extra provenance for [notes].

    A safety fault, a device error or Ctrl-C ends the run with ``status = "fault"`` and the
    reason; any other exception is recorded the same way and raised again. In every case 0 V
    is written and the device stopped before this returns.
    """
    limits = limits or Limits()
    check_controller(pid, limits)
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
    ref = [float(r) for r in np.asarray(reference, dtype=float).ravel()]
    n = len(ref)
    if n < 2:
        raise ValueError(f"the reference has {n} sample(s); give at least 2 (duration > Ts)")
    ts = float(pid.sample_time)
    law = float_pid(pid)

    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    run_table = {"status": "running", "started": started, "clock": clock}
    safety_table = {
        f"limit_{k}": (float(v) if isinstance(v, float) else v) for k, v in limits.to_dict().items()
    }
    device_table = {**device.describe(), "clock": clock}
    recorder = None
    if out is not None:
        tables = {"device": device_table, "run": {**run_table, **safety_table}}
        if notes:
            tables["notes"] = dict(notes)
        recorder = RunRecorder(
            out, pid, description=description, tables=tables, flush_every=flush_every
        )

    log_y, log_u, log_tw, log_c = [], [], [], []
    guard = Guard(limits, ts)
    perf = time.perf_counter
    sleep = time.sleep
    virtual = clock == "virtual"
    paced = clock == "perf_counter"
    fault = None
    error = None
    stop_note = None
    k = 0
    gc_was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    if not virtual:
        gc.disable()
    try:
        device.start(ts)
        state = None
        t0 = perf() + (2 * SPIN if paced else 0.0)
        for k in range(n):
            kts = k * ts
            if paced:
                deadline = t0 + kts
                remaining = deadline - perf()
                if remaining > SPIN:
                    sleep(remaining - SPIN)
                while perf() < deadline:
                    pass
            y = device.read()
            t_read = perf()
            if k == 0 and not paced:
                t0 = t_read
            t_wall = kts if virtual else t_read - t0
            r = ref[k]
            log_y.append(y)
            log_u.append(0.0)  # the 0 V of the finally, should this sample fault
            log_tw.append(t_wall)
            log_c.append(0.0)
            if not virtual:
                guard.check_late(k, t_wall - kts)
            guard.check_position(k, y)
            if state is None:
                s = pid_init(law, r, y, xp=np)
                state = PIDState(float(s.integral), float(s.derivative), float(s.previous))
            u, _, state = pid_update(law, state, r, y, xp=_Floats, clip=_clip)
            u = guard.clamp(u)
            device.write(u)
            compute = perf() - t_read
            log_u[-1] = u
            log_c[-1] = compute
            if recorder is not None:
                recorder.row(kts, y, u, r, t_wall, compute)
        k = n
    except Fault as exc:
        fault = str(exc)
    except DeviceError as exc:
        fault = f"device: {exc}"
    except KeyboardInterrupt:
        fault = f"interrupted (Ctrl-C) at t = {k * ts:.3f} s"
    except BaseException as exc:
        fault = f"error: {type(exc).__name__}: {' '.join(str(exc).split())}"
        error = exc
    finally:
        try:
            device.write(0.0)
        except BaseException as exc:  # noqa: BLE001 - stop() below tries again
            stop_note = f"writing 0 V failed: {exc}"
        try:
            device.stop()
        except BaseException as exc:  # noqa: BLE001 - the recording must still be closed
            stop_note = f"stopping the device failed: {exc}"
        if gc_was_enabled:
            gc.enable()
        gc.unfreeze()

    m = len(log_y)
    if recorder is not None and fault is not None and m > recorder.rows:
        # The faulting sample: its position as read, the 0 V that was written.
        recorder.row((m - 1) * ts, log_y[-1], 0.0, ref[m - 1], log_tw[-1], log_c[-1])
    t_wall = np.asarray(log_tw, dtype=float)
    compute = np.asarray(log_c, dtype=float)
    timing = timing_stats(t_wall, compute, ts, virtual=virtual)
    status = "completed" if fault is None else "fault"
    run_final = {**run_table, "status": status, "samples": m, "duration": m * ts}
    if fault is not None:
        run_final["fault"] = fault
    if stop_note:
        run_final["stop"] = stop_note
    stop_errors = getattr(device, "stop_errors", None)
    if stop_errors:
        run_final["stop_errors"] = "; ".join(stop_errors)
    run_final["last_voltage"] = float(device.last_voltage)
    device_table = {**device.describe(), "clock": clock}  # as started (e.g. the watchdog)
    path = None
    if recorder is not None:
        path = recorder.close({"run": run_final, "timing": timing, "device": device_table})
    result = RunResult(
        status=status,
        fault=fault,
        time=np.arange(m) * ts,
        position=np.asarray(log_y, dtype=float),
        command=np.asarray(log_u, dtype=float),
        reference=np.asarray(ref[:m], dtype=float),
        t_wall=t_wall,
        compute=compute,
        timing=timing,
        path=path,
        device=device_table,
    )
    if error is not None:
        raise error
    return result


def timing_stats(t_wall, compute, sample_time: float, *, virtual: bool = False) -> dict:
    """Sample-period and compute-time statistics of a run, in microseconds ([timing]).

    period: steps of t_wall; late: t_wall - k Ts; overruns: samples whose write ended after the
    next deadline (per 10,000 samples too). In virtual time only the compute times mean anything.
    """
    n = int(np.size(t_wall))
    stats: dict = {"samples": n, "sample_time_us": sample_time * 1e6}
    if n == 0:
        return stats
    us = 1e6
    stats["compute_median_us"] = float(np.median(compute)) * us
    stats["compute_p99_us"] = float(np.percentile(compute, 99)) * us
    stats["compute_max_us"] = float(np.max(compute)) * us
    if virtual or n < 2:
        return stats
    period = np.diff(t_wall)
    late = t_wall - np.arange(n) * sample_time
    over = int(np.count_nonzero(t_wall + compute > (np.arange(n) + 1) * sample_time))
    stats.update(
        period_median_us=float(np.median(period)) * us,
        period_p99_us=float(np.percentile(period, 99)) * us,
        period_max_us=float(np.max(period)) * us,
        period_min_us=float(np.min(period)) * us,
        late_max_us=float(np.max(late)) * us,
        overruns=over,
        overruns_per_10000=over * 10000.0 / n,
    )
    return {
        k: (round(v, 3) if isinstance(v, float) and math.isfinite(v) else v)
        for k, v in stats.items()
    }
