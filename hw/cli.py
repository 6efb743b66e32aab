"""``python -m hw``: run tuned gains on the cart, and measure the loop. Numpy only.

    python -m hw run GAINS.json --device sim --step 0.5 [--duration 3] [--out RUN.toml]
    python -m hw run GAINS.json --device sim --step 0.5 --real-time     # paced at 1/Ts
    python -m hw run GAINS.json --device q2_usb --slider 0.2,0,-0.2,0.2 [--hold 2]
    python -m hw run GAINS.json --device replay --replay OLD.toml
    python -m hw bench [--samples 10000]

Before the run the gains are simulated (hw.prerun: refused when unstable or a relay, unless
--force); after it, the metrics of the run are printed against the spec and that simulation,
with the pacing's verdict (hw.pacing), and against the prediction the gains file carries
(hw.predicted: ``jaxcart lab`` writes the band of its design on the cart as measured): inside
the band, or which fitted value of the cart would explain the difference. Exit status: 0
completed, 1 a fault or an error, 2 bad options or an output that cannot be written (nothing
moved), 128 + the signal's number when a signal stopped the run (130 Ctrl-C, 143 SIGTERM, 129
SIGHUP).

``jaxcart run`` (tuning/commands/run.py) is the same command from the full install.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from hw.control_law import PID
from hw.devices.base import DeviceError
from hw.devices.quanser import QuanserBoard
from hw.devices.replay import Replay
from hw.devices.sim import CartParams, SimCart, load_cart_params
from hw.expfile import ExpFileError
from hw.gains import GainsFileError, read_gains_file
from hw.loop import run_loop, timing_stats
from hw.pacing import choose_watchdog, verdict
from hw.predicted import check_lines, check_run
from hw.prerun import check_gains
from hw.safety import X_MAX, Limits
from hw.stepinfo import comparison_lines, run_metrics, spec_of

DEVICES = ("sim", "q2_usb", "q8_usb", "replay")
#: Default folder and name of recordings (never overwritten: run.toml, run-2.toml, ...).
OUT_DIR = Path("jaxcart-out")
OUT_STEM = "hw-run"


class CommandError(ValueError):
    """Bad options: printed as one line."""


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``run`` (shared by ``python -m hw run`` and ``jaxcart run``)."""
    p.add_argument("gains", metavar="GAINS.json", help="gains file from `jaxcart tune`")
    p.add_argument(
        "--device",
        default="sim",
        help=f"{', '.join(DEVICES)} or another Quanser HIL board type (default: sim)",
    )
    p.add_argument("--board-id", default="0", help="which board of that type (default: 0)")
    ref = p.add_mutually_exclusive_group()
    ref.add_argument("--step", type=float, metavar="M", help="reference step [m] at t = 0")
    ref.add_argument(
        "--slider",
        metavar="R1,R2,...",
        help="reference set points [m], each held for --hold s (the handout's Part (v))",
    )
    p.add_argument("--hold", type=float, default=2.0, metavar="S", help="seconds per set point")
    p.add_argument("--duration", type=float, metavar="S", help="run time [s] (default 3 s)")
    p.add_argument("--out", metavar="RUN.toml", help="the recording (default: jaxcart-out/...)")
    p.add_argument("--plant", metavar="FILE", help="sim: cart parameters (TOML/JSON, name = value)")
    p.add_argument("--replay", metavar="REC.toml", help="replay: the recording to play back")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument(
        "--virtual",
        action="store_true",
        help="sim/replay: no real time, as fast as possible (their default)",
    )
    pace.add_argument(
        "--real-time",
        action="store_true",
        help="sim/replay: pace the loop at 1/Ts on the computer's clock, as on the cart",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="run gains the simulation refuses (unstable, or a relay at the voltage limit)",
    )
    p.add_argument("--x-max", type=float, default=X_MAX, help=f"track limit [m] ({X_MAX})")
    p.add_argument("--v-max", type=float, default=6.0, help="voltage clamp [V] (6)")
    p.add_argument("--speed-max", type=float, default=1.5, help="velocity limit [m/s] (1.5)")
    p.add_argument("--jump-max", type=float, default=0.005, help="encoder jump limit [m] (0.005)")
    p.add_argument(
        "--watchdog",
        type=float,
        metavar="S",
        help="loop watchdog: a sample read more than S seconds late stops the run (default: "
        "chosen for this machine by a 0.2 s probe, 5-50 ms; 0: off)",
    )
    p.add_argument("--encoder-channel", type=int, default=0)
    p.add_argument("--analog-channel", type=int, default=0)
    p.add_argument("--description", help="text for the recording's description")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m hw", description="Run tuned gains on the cart (numpy only)."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    p = sub.add_parser("run", help="run a gains file on a device and record the run")
    add_run_arguments(p)
    p.set_defaults(func=run_command)
    b = sub.add_parser("bench", help="the loop's cost per sample and its real-time jitter")
    b.add_argument("--samples", type=int, default=10000, help="samples per real-time run")
    b.set_defaults(func=bench_command)
    return parser


def main(argv=None, *, exiting: bool = False) -> int:
    """The command line; ``exiting``: the process ends after this (``python -m hw``), so a
    signal that arrives after a run is ignored to the end instead of raising at the exit."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.exiting = exiting
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (CommandError, GainsFileError, ExpFileError, DeviceError, ValueError) as exc:
        print(f"hw {args.command}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # outside the loop (which handles its own): nothing was driven
        print(f"hw {args.command}: interrupted (Ctrl-C)", file=sys.stderr)
        return 130


# ---------------------------------------------------------------- run


def reference_from(args, sample_time: float) -> np.ndarray:
    """r_k [m] from --step / --slider, --hold and --duration."""
    if args.slider is not None:
        try:
            points = [float(x) for x in args.slider.split(",") if x.strip()]
        except ValueError:
            raise CommandError(
                f"--slider {args.slider!r}: give set points in m, e.g. 0.2,0,-0.2"
            ) from None
        if not points:
            raise CommandError("--slider: give at least one set point")
        if not (math.isfinite(args.hold) and args.hold > 0):
            raise CommandError(f"--hold {args.hold!r}: give a positive number of seconds")
        duration = args.duration if args.duration is not None else args.hold * len(points)
        segments = np.repeat(points, int(round(args.hold / sample_time)))
    else:
        amplitude = 0.5 if args.step is None else args.step
        duration = 3.0 if args.duration is None else args.duration
        segments = np.array([amplitude])
    if not (math.isfinite(duration) and duration > 0):
        raise CommandError(f"--duration {duration!r}: give a positive number of seconds")
    n = int(round(duration / sample_time)) + 1
    k = np.minimum(np.arange(n), segments.size - 1)
    r = np.asarray(segments, dtype=float)[k]
    if args.x_max is not None and np.any(np.abs(r) >= args.x_max):
        raise CommandError(
            f"the reference reaches {np.abs(r).max():g} m, at or beyond the track limit "
            f"--x-max {args.x_max:g} m; give set points inside it"
        )
    return r


def make_device(args):
    """The device named by --device (the Quanser API is imported only when a board starts)."""
    name = args.device
    if name != "sim" and args.plant:
        raise CommandError("--plant sets the simulated cart; use it with --device sim")
    if name != "replay" and args.replay:
        raise CommandError("--replay names the recording of --device replay")
    if name == "sim":
        return SimCart(load_cart_params(args.plant) if args.plant else CartParams())
    if name == "replay":
        if not args.replay:
            raise CommandError("--device replay needs --replay REC.toml, the recording to play")
        return Replay(args.replay)
    if args.virtual:
        raise CommandError(f"--virtual: {name} is real hardware, it runs in real time only")

    return QuanserBoard(
        name,
        args.board_id,
        encoder_channel=args.encoder_channel,
        analog_channel=args.analog_channel,
    )


def free_names(folder: Path, stem: str) -> Path:
    """``folder/stem.toml`` or ``stem-2.toml``, ...: the first whose TOML and CSV are both free."""
    n = 1
    while True:
        name = stem if n == 1 else f"{stem}-{n}"
        toml, csv = folder / f"{name}.toml", folder / f"{name}.csv"
        if not (toml.exists() or csv.exists()):
            return toml
        n += 1


def _limits(args, clock: str | None, sample_time: float) -> tuple[Limits, str | None]:
    """The run's limits; the watchdog chosen for this machine unless --watchdog gives it."""
    how = None
    late_max = args.watchdog
    if late_max is None:
        if clock == "virtual":
            late_max = 0.0  # not checked in virtual time
        else:
            late_max, how = choose_watchdog(sample_time)
    try:
        limits = Limits(
            x_max=args.x_max,
            v_max=args.v_max,
            speed_max=args.speed_max,
            jump_max=args.jump_max,
            late_max=late_max,
        )
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    return limits, how


def _clock(args, device) -> str | None:
    """sim and replay run in virtual time unless --real-time; a board on its own clock."""
    if args.real_time:
        if not device.virtual:
            raise CommandError(f"--real-time: {args.device} is real hardware, always real time")
        return "perf_counter"
    if device.virtual:
        return "virtual"
    return None


def _check(pid, reference, limits, force: bool):
    """The pre-run plausibility (hw.prerun): refuse unstable or relay gains unless forced."""
    check = check_gains(pid, reference, limits)
    for line in check.warnings:
        print(f"hw run: warning: {line}", file=sys.stderr)
    if check.refusals and not force:
        raise CommandError("; ".join(check.refusals) + " (--force runs them anyway)")
    for line in check.refusals:
        print(f"hw run: warning (--force): {line}", file=sys.stderr)
    return check


def run_command(args) -> int:
    pid, meta = read_gains_file(args.gains)
    _limits(args, "virtual", pid.sample_time)  # the numbers checked first (no probe yet)
    reference = reference_from(args, pid.sample_time)
    device = make_device(args)
    clock = _clock(args, device)
    limits, how = _limits(args, clock, pid.sample_time)
    check = _check(pid, reference, limits, args.force)
    out = Path(args.out) if args.out else free_names(OUT_DIR, OUT_STEM)
    notes = {"gains": str(Path(args.gains).resolve())}
    if isinstance(meta.get("date"), str):
        notes["gains_date"] = meta["date"]
    if check.refusals:
        notes["forced"] = "; ".join(check.refusals)
    if how:
        notes["watchdog"] = how
    what = f"step {reference[-1]:g} m" if args.slider is None else f"slider {args.slider} m"
    description = args.description or f"hw run: {what} on {args.device}"
    pacing = {
        "virtual": "virtual time (as fast as possible; --real-time paces it at 1/Ts)",
        "perf_counter": "real time on the computer's clock",
        None: "real time on the board's clock",
    }[clock]
    print(
        f"hw run: {args.device} in {pacing}, {reference.size} samples at "
        f"{pid.sample_time * 1e3:g} ms, kp={pid.kp:g} ki={pid.ki:g} kd={pid.kd:g}, writing {out}",
        file=sys.stderr,
    )
    if how:
        print(f"hw run: {how}", file=sys.stderr)
    held = _HeldSignals()
    try:
        try:
            result = run_loop(
                device,
                pid,
                reference,
                limits=limits,
                clock=clock,
                out=out,
                description=description,
                notes=notes,
            )
        finally:
            held.hold()  # the run is over: later signals must not cut the report short
    except Exception as exc:  # recorded, 0 V written: one line, not a traceback
        result = getattr(exc, "run_result", None)
        if result is None:  # refused before anything was driven (an existing --out, ...)
            held.release()
            raise
        print(
            f"hw run: stopped by an error in the software: {type(exc).__name__}: "
            f"{' '.join(str(exc).split())}; {zero_volts(result)}",
            file=sys.stderr,
        )
        if result.path is not None:
            print(result.path)
        held.release()
        return 1
    try:
        return _report(result, check.simulated, meta)
    finally:
        if not getattr(args, "exiting", False):  # else held until the process ends
            held.release()


class _HeldSignals:
    """After the loop: stopping signals are noted and ignored until the report is printed (a
    fourth Ctrl-C must not leave a traceback after the run was stopped and recorded)."""

    NAMES = ("SIGINT", "SIGTERM", "SIGHUP", "SIGBREAK")

    def __init__(self):
        self._old: dict = {}
        self.received: list[str] = []

    def hold(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for name in self.NAMES:
            signum = getattr(signal, name, None)
            if signum is not None:
                try:
                    self._old[signum] = signal.signal(signum, self._note)
                except (OSError, ValueError):
                    pass

    def _note(self, signum, frame) -> None:
        self.received.append(signal.Signals(signum).name)

    def release(self) -> None:
        for signum, old in self._old.items():
            try:
                signal.signal(signum, old if old is not None else signal.SIG_DFL)
            except (OSError, ValueError):
                pass
        self._old = {}


def _report(result, simulated, meta) -> int:
    """Print how the run went (metrics against the spec and the simulation); exit status."""
    t = result.timing
    print(f"hw run: {result.status}, {result.n_samples} samples", file=sys.stderr)
    if "compute_median_us" in t:
        print(
            f"hw run: {verdict(t)}; compute median {t['compute_median_us']:.1f} us", file=sys.stderr
        )
    if result.fault is None and result.n_samples >= 2:
        sim = run_metrics(simulated) if simulated is not None else None
        measured = run_metrics(result)
        for line in comparison_lines(measured, sim, spec_of(meta)):
            print(f"hw run: {line}", file=sys.stderr)
        for line in prediction_lines(measured, meta):
            print(f"hw run: {line}", file=sys.stderr)
    for note in result.notes:
        print(f"hw run: note: {note}", file=sys.stderr)
    if result.fault:
        print(f"hw run: stopped: {result.fault}; {zero_volts(result)}", file=sys.stderr)
    elif not result.zero_written:
        print(f"hw run: at the end: {zero_volts(result)}", file=sys.stderr)
    if result.path is not None:
        print(result.path)
    return exit_status(result)


def prediction_lines(measured: list[dict], meta: dict) -> list[str]:
    """The run's first step against the prediction in the gains file's metadata (none: no
    lines): inside its band, or which fitted value would explain the difference."""
    prediction = meta.get("prediction") if isinstance(meta, dict) else None
    if not isinstance(prediction, dict) or not measured:
        return []
    first = measured[0]
    step = prediction.get("step")
    if isinstance(step, int | float) and not math.isclose(first["set_point"], step, abs_tol=1e-9):
        return [
            f"the gains file predicts a {step:g} m step; this run stepped to "
            f"{first['set_point']:g} m, so it is not compared (--step {step:g})"
        ]
    return ["against the prediction of the gains file:"] + [
        f"  {line}" for line in check_lines(check_run(first, prediction))
    ]


def zero_volts(result) -> str:
    """Whether 0 V reached the device at the end, said as it is (the run's last line)."""
    if result.zero_written and result.n_samples == 0:
        return "nothing was driven (the device stopped before its first sample)"
    if result.zero_written:
        return "0 V written and the device stopped"
    held = (
        f"may still hold {result.last_voltage:.4g} V, the last voltage it took"
        if math.isfinite(result.last_voltage)
        else "holds an unknown voltage"
    )
    return (
        f"writing 0 V FAILED ({result.zero_failure}): the output {held}; switch the amplifier off"
    )


def exit_status(result) -> int:
    """0 completed; 128 + the signal's number when one stopped the run (130 Ctrl-C, 143
    SIGTERM, 129 SIGHUP); 1 any other fault."""
    if result.signals:
        number = getattr(signal, result.signals[0], None)
        return 128 + int(number) if number is not None else 1
    return 0 if result.status == "completed" else 1


# ---------------------------------------------------------------- bench


class _NullDevice:
    """No physics, no I/O: what is left is the loop's own cost."""

    name = "null"
    hardware_timed = False
    virtual = True
    last_voltage = 0.0

    def start(self, sample_time):
        pass

    def read(self):
        return 0.0

    def write(self, volts):
        self.last_voltage = volts

    def stop(self):
        self.last_voltage = 0.0

    def describe(self):
        return {"name": self.name}


def _naive_periods(n: int, ts: float) -> tuple[np.ndarray, np.ndarray]:
    """A loop that does its work then time.sleep(Ts): the timestamps and the work times."""
    stamps, work = np.empty(n), np.empty(n)
    perf = time.perf_counter
    t0 = perf()
    for k in range(n):
        t = perf()
        stamps[k] = t - t0
        work[k] = perf() - t
        time.sleep(ts)
    return stamps, work


def bench_command(args) -> int:
    n = int(args.samples)
    if n < 100:
        raise CommandError(f"--samples {n}: give at least 100")
    pid = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
    ts = pid.sample_time
    ref = np.full(n, 0.0)
    print(f"hw bench: PID kp=40 kd=5 ki=5, 6 V, Ts = {ts * 1e3:g} ms, {n} samples per run")
    print("loop cost per sample (virtual time, no waiting):")
    run_loop(_NullDevice(), pid, ref[:1000], clock="virtual")  # warm-up
    for label, device, r in (
        ("null device (the loop alone)", _NullDevice(), ref),
        ("simulated cart, step 0.5 m", SimCart(), np.full(n, 0.5)),
    ):
        t = time.perf_counter()
        res = run_loop(device, pid, r, clock="virtual", limits=Limits(x_max=1e9))
        per = (time.perf_counter() - t) / n * 1e6
        c = res.timing
        print(
            f"  {label:32s} {per:7.2f} us/sample (read->write median "
            f"{c['compute_median_us']:.2f} us, p99 {c['compute_p99_us']:.2f} us)"
        )
    print(f"real time at {1 / ts:g} Hz, {n} samples each (sample period in us):")
    res = run_loop(_RealNull(), pid, ref, clock="perf_counter", limits=Limits(late_max=0))
    rows = [("hw loop (sleep + spin, absolute deadlines)", res.timing)]
    stamps, work = _naive_periods(n, ts)
    rows.append(("naive time.sleep(Ts) loop", timing_stats(stamps, work, ts)))
    print(
        f"  {'':44s} {'median':>8s} {'p99':>8s} {'max':>9s} {'overruns/10k':>13s} "
        f"{'>1.5Ts/10k':>11s}"
    )
    for (label, t), wall in zip(rows, (res.t_wall, stamps), strict=True):
        long = np.count_nonzero(np.diff(wall) > 1.5 * ts) * 10000.0 / (wall.size - 1)
        print(
            f"  {label:44s} {t['period_median_us']:8.1f} {t['period_p99_us']:8.1f} "
            f"{t['period_max_us']:9.1f} {t['overruns_per_10000']:13.1f} {long:11.1f}"
        )
    print(
        "  overruns: samples whose write ended after the next deadline k Ts of an absolute "
        "schedule (a loop that drifts overruns every sample); >1.5Ts: periods over 1.5 ms"
    )
    return 0


class _RealNull(_NullDevice):
    virtual = False
