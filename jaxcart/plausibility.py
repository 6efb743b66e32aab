"""Does a recording, or a controller, make physical sense for the lab's cart?

A file in the wrong units or with the wrong gains reads without complaint and then gives absurd
fits (a tap in mm "fits" f_c = 461 N). These checks run whenever a recording is read
(:func:`jaxcart.files.read_experiment`) and before a simulation:

- positions: the track is 0.99 m long and the cart travels 0.814 m (``jaxcart.params``);
  positions far beyond that are an error that names the likely unit, beyond the travel a warning;
- velocity and acceleration (warnings only: test signals are often faster) against what the
  plant can reach at its voltage limit V (the software limit or amplifier saturation, else
  6 V, the lab's range): the steady speed gamma V / c and the acceleration 2 gamma V / m
  (full voltage against full-speed damping);
  a tap (motor unplugged, pushed by hand) must coast to rest within the travel, so v(0) <=
  travel c / m, and its push has no limit;
- the sample time against the lab's 1 kHz loop;
- an open loop's input voltage: beyond what any amplifier of the lab gives it is an error that
  names the likely unit (a column in mV), as the closed loop's command is checked against
  its controller below; a motion far smaller than the nominal cart makes of that input is a
  warning;
- the recorded command against the command the file's own controller computes from the
  recorded position and reference (:mod:`hw.control_law`, up to a sample of delay);
- the controller: the eigenvalues of the discrete closed loop of the linear part (nominal
  plant with zero-order hold, behind the plant's transport ``delay`` when it has one, split
  sample included; the PID with its derivative filter): unstable when one lies outside the
  unit circle; implausible when its linear range v_limit / kp is below one encoder
  count (the loop is a relay), when one count of noise swings the derivative term over the
  whole range, or when a mode rings faster than the 1 kHz loop resolves (above fs / 8, judged
  on the loop without the delay, whose delay line has fast poles of its own).

Before a fit (:func:`check_fit_recordings`, called at the top of
:func:`tuning.estimation.fit.fit`): a recording in which the cart does not move (amplifier off)
and the same data given twice are refused, where a fit would otherwise report a friction of
1e55 kg/s or standard errors sqrt(2) too small.

Errors are :class:`UserError` (one line: file, column, value, fix); warnings are strings, which
:func:`warn` prints once to stderr.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from hw.control_law import float_pid, pid_init, pid_update, setting_problem
from hw.expfile import time_scatter
from jaxcart.effects import Delay
from jaxcart.errors import UserError
from jaxcart.params import ENCODER_RESOLUTION, TRACK_LENGTH, TRAVEL, voltage_limit

#: The lab amplifier's range [V] when neither the controller nor the plant states a limit.
LAB_VOLTAGE = 6.0
#: Positions beyond this many track lengths are a unit error, not a cart off its track.
ABSURD_TRACK_LENGTHS = 5.0
#: A closed-loop recording with integral action whose clock starts this late [s] may hold
#: only the end of its run (:func:`check_integral_start`).
LATE_START = 1.0
#: Margin on the velocity and acceleration limits before a warning (a lower B_eq than the
#: nominal, the transient of a step, difference noise).
MARGIN = 1.5
#: Window of the differences that estimate velocity and acceleration [s] (one encoder count
#: over 10 ms is 2.3 mm/s, and 0.45 m/s^2 in the second difference).
DIFF_WINDOW = 0.01
#: Sample times the lab's loop runs at [s]: outside, a warning (the lab runs at 1 kHz).
SAMPLE_TIME_RANGE = (1e-4, 0.02)
#: The recorded command agrees with the file's controller when the median |difference| is
#: below COMMAND_TOL_V + COMMAND_TOL_REL * max |command| (rounding, DAC quantization): the
#: lab's recordings agree to 1 mV, gains 10 % off differ by 15-26 mV (6 V peak).
COMMAND_TOL_V = 0.01
COMMAND_TOL_REL = 0.001
#: Closed-loop modes above fs / 8 are beyond what the sampled loop resolves.
MAX_MODE_FRACTION = 1.0 / 8.0
#: Eigenvalues this far outside the unit circle are unstable (an integrator sits on it).
UNIT_CIRCLE_TOL = 1e-6
#: The most voltage a lab amplifier puts on the motor [V] (Quanser's VoltPAQ-X1 at gain 3 gives
#: +-24 V; the lab's own range is LAB_VOLTAGE): an open-loop input beyond it is in other units.
AMPLIFIER_VOLTAGE = 24.0
#: An open loop whose cart moves less than this fraction of what the nominal linear cart (no
#: friction) makes of its input is doubtful (friction, 0.3-0.5 N, takes a part; an input 1000
#: times too large, in mV, takes nearly all).
MOTION_FRACTION = 0.02
#: Fewer encoder counts of motion than this in a whole recording: the cart did not move (the
#: diagnosis's own floor, tuning.estimation.diagnose.policy.MIN_COUNTS).
MIN_MOTION_COUNTS = 20

_printed: set[str] = set()


def warn(message: str) -> None:
    """Print a warning to stderr, once per process for each distinct message."""
    if message in _printed:
        return
    _printed.add(message)
    print(f"jaxcart: warning: {message}", file=sys.stderr)


# ---------------------------------------------------------------- recordings


def check_recording(rec) -> list[str]:
    """Check a :class:`jaxcart.files.Recording` for physical sense: raises :class:`UserError`
    for clear absurdities (positions in mm), returns the warnings (strings, not printed)."""
    # Values near the float range overflow in differences: inf is then the honest answer.
    with np.errstate(over="ignore", invalid="ignore"):
        return _check_recording(rec)


def _check_recording(rec) -> list[str]:
    where = str(rec.path)
    y = np.asarray(rec.position, dtype=float)
    warnings = []
    warnings += _check_positions(where, _label(rec, "y"), y)
    warnings += _check_sample_time(where, rec.sample_time)
    warnings += _check_time_jitter(where, _label(rec, "t"), rec)
    plant = rec.plant()
    volts = _voltage_range(rec, plant)
    warnings += _check_motion(where, _label(rec, "y"), rec, plant, volts)
    warnings += _check_start_at_rest(where, _label(rec, "y"), rec, plant, volts)
    warnings += _check_tap_ends_at_rest(where, _label(rec, "y"), rec)
    warnings += check_integral_start(where, rec)
    if rec.kind == "open_loop":
        warnings += check_input_units(rec, plant)
    if rec.kind == "closed_loop" and rec.controller is not None:
        warnings += check_controller(rec.controller, plant, where=f"{where} [controller]")
        if rec.command is not None:
            warnings += _check_command(where, _label(rec, "v"), rec)
    return warnings


def _label(rec, column: str) -> str:
    data = rec.meta.get("data")
    if isinstance(data, dict):
        return f"[data] {column} ({data.get(column, '?')})"
    return f"{data} column {column}"


def _check_positions(where, label, y) -> list[str]:
    extent = float(max(np.max(np.abs(y)), np.ptp(y)))
    if extent > ABSURD_TRACK_LENGTHS * TRACK_LENGTH:
        units = [(u, f) for u, f in (("cm", 100), ("mm", 1000)) if extent / f <= TRACK_LENGTH]
        if len(units) == 2:
            guess = "recorded in cm (or mm)? divide by 100 (or 1000) for metres"
        elif units:
            guess = f"recorded in {units[0][0]}? divide by {units[0][1]} for metres"
        elif np.all(y == np.rint(y)) and extent * ENCODER_RESOLUTION <= TRACK_LENGTH:
            guess = (  # the encoder's counts, as the QUARC block outputs them before its gain
                f"whole numbers: encoder counts? multiply by {ENCODER_RESOLUTION:g} (m per "
                "count) for metres"
            )
        else:
            guess = "not a position in metres? convert it to metres"
        raise UserError(
            f"{where}: {label}: positions up to {extent:.4g} m on a {TRACK_LENGTH} m track: "
            f"{guess} (docs/experiment-files.md: y is in m)"
        )
    if float(np.ptp(y)) > TRAVEL * 1.02:
        return [
            f"{where}: {label}: the cart moves over {float(np.ptp(y)):.3g} m, more than its "
            f"{TRAVEL} m travel (the end stops); a run off the track, or positions not in m?"
        ]
    return []


def _check_sample_time(where, ts) -> list[str]:
    low, high = SAMPLE_TIME_RANGE
    if low <= ts <= high:
        return []
    hint = " (time recorded in ms? give t in s)" if ts > high else ""
    return [
        f"{where}: sample time {ts:g} s is outside {low:g}-{high:g} s; the lab's loop runs at "
        f"1 kHz (0.001 s){hint}"
    ]


def _check_time_jitter(where, label, rec) -> list[str]:
    """Time stamps that scatter about the uniform grid t_0 + k Ts by more than 1 % of a sample
    (a logger's own clock, read with jitter): said, since the samples are taken as k Ts."""
    t = np.asarray(rec.time, dtype=float)
    ts = float(rec.sample_time)
    if t.size < 2:
        return []
    worst = time_scatter(t, ts)
    if not worst > 0.01 * ts:
        return []
    return [
        f"{where}: the time stamps of {label} scatter by up to {worst * 1e6:.3g} us "
        f"({100 * worst / ts:.3g} % of a sample) about a uniform {ts:g} s step; the samples are "
        "taken as uniform in time, as the controller's loop ran them (a clock read with jitter)"
    ]


def time_unit_doubt(rec) -> str | None:
    """Why a result from ``rec`` cannot be trusted because of its time base, said for the
    error that ends a command (the reading's warning has scrolled away by then): a sample
    time that is a lab one in milliseconds; None when the time base is plausible."""
    low, high = SAMPLE_TIME_RANGE
    ts = float(rec.sample_time)
    if ts > high and low <= ts / 1000 <= high:
        return (
            f"its time looks recorded in milliseconds (sample time {ts:g} s, where the lab's "
            f"loop runs at 0.001 s): give t in s (divide the column by 1000)"
        )
    return None


def _voltage_range(rec, plant) -> float:
    """The largest voltage the cart can have received [V] (see the module docstring)."""
    limit = float(voltage_limit(plant, rec.controller))
    if math.isfinite(limit):
        return limit
    if rec.command is not None:
        return max(LAB_VOLTAGE, float(np.max(np.abs(rec.command))))
    if rec.kind == "open_loop":
        return max(LAB_VOLTAGE, float(np.max(np.abs(np.asarray(rec.experiment.signal)))))
    return LAB_VOLTAGE


def _differences(y, ts):
    w = max(1, int(round(DIFF_WINDOW / ts)))
    if y.size <= 2 * w:
        return None, None
    h = w * ts
    velocity = (y[w:] - y[:-w]) / h
    acceleration = (y[2 * w :] - 2 * y[w:-w] + y[: -2 * w]) / h**2
    return velocity, acceleration


def _check_motion(where, label, rec, plant, volts) -> list[str]:
    y = np.asarray(rec.position, dtype=float)
    velocity, acceleration = _differences(y, rec.sample_time)
    if velocity is None:
        return []
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    if rec.kind == "tap":
        v_max = TRAVEL * c / m if c > 0 else math.inf
        why = f"a tap coasting to rest within the {TRAVEL} m travel (travel c/m, c = {c:.3g} kg/s)"
        limits = [("velocity", velocity, v_max, "m/s", why)]
    else:
        v_max = gamma * volts / c if c > 0 else math.inf
        a_max = 2 * gamma * volts / m
        limits = [
            ("velocity", velocity, v_max, "m/s", f"gamma V/c at V = {volts:g} V"),
            ("acceleration", acceleration, a_max, "m/s^2", f"2 gamma V/m at V = {volts:g} V"),
        ]
    out = []
    for what, values, limit, unit, why in limits:
        peak = float(np.max(np.abs(values)))
        if peak > MARGIN * limit:
            out.append(
                f"{where}: {label}: {what} up to {peak:.3g} {unit}, {peak / limit:.3g} times "
                f"what the cart can reach ({limit:.3g} {unit}, {why}); positions not in m, "
                f"time not in s, or a wrong [plant]?"
            )
    return out


def _edge_motion(rec, last: bool) -> tuple[float, float] | None:
    """(distance [m], span [s]) the cart covers over DIFF_WINDOW at the first (or ``last``)
    samples of ``rec``; None where the recording is shorter."""
    y = np.asarray(rec.position, dtype=float)
    ts = float(rec.sample_time)
    w = max(1, int(round(DIFF_WINDOW / ts)))
    if y.size <= w:
        return None
    return abs(float(y[-1] - y[-1 - w] if last else y[w] - y[0])), w * ts


def _check_tap_ends_at_rest(where, label, rec) -> list[str]:
    """A tap recorded until the cart rests: one cut while it still coasts (over 3 counts in
    its last DIFF_WINDOW) loses the stop, where Coulomb friction shows apart from B_eq."""
    edge = _edge_motion(rec, last=True) if rec.kind == "tap" else None
    if edge is None or edge[0] <= 3 * ENCODER_RESOLUTION:
        return []
    return [
        f"{where}: {label}: the cart still moves at {edge[0] / edge[1]:.3g} m/s at the last "
        "sample: the tap was cut before the cart came to rest, and B_eq and f_c are hard to "
        "tell apart without its stop; record until the cart rests"
    ]


def check_integral_start(where, rec) -> list[str]:
    """A run under integral action is simulated with its integral at 0 at the first sample: a
    recording whose clock starts :data:`LATE_START` or later may hold only a run's end (a
    scope that kept its last samples), when the integral had built up, which nothing recorded
    says (the cart may even be at rest there, so the moving-start check sees nothing); or an
    error scope that the import noted starts far below the handout's step
    (:func:`jaxcart.matimport.late_start`)."""
    pid = rec.controller
    if rec.kind != "closed_loop" or pid is None or float(pid.ki) == 0.0:
        return []
    t0 = float(np.asarray(rec.time)[0])
    if not t0 >= LATE_START:  # the clock says nothing: what the import noted, if anything
        notes = rec.meta.get("notes")
        late = notes.get("late_start") if isinstance(notes, dict) else None
        return [f"{where}: {late} (noted by jaxcart import)"] if isinstance(late, str) else []
    data = rec.meta.get("data")
    label = "the data's time" if isinstance(data, dict) and "t" not in data else _label(rec, "t")
    return [
        f"{where}: {label}: the time starts at t = {t0:g} s: if the run started before the "
        f"recording did (a scope that kept only its last samples), its integral (ki = "
        f"{float(pid.ki):g} V/(m s)) had built up by then, where the simulations start it at 0 "
        "at the first sample; record the run from its step (or cut the rows before the step)"
    ]


def _check_start_at_rest(where, label, rec, plant, volts) -> list[str]:
    """A driven run is simulated from rest (``initial_velocity`` 0, unless the file gives
    one): a cart that covers, in its first DIFF_WINDOW, more than full voltage could drive it
    from rest (and two counts) was already moving: the recording started late."""
    if rec.kind == "tap" or "initial_velocity" in rec.meta:
        return []
    edge = _edge_motion(rec, last=False)
    if edge is None:
        return []
    moved, h = edge
    from_rest = 0.5 * float(plant.gamma) * volts / float(plant.m) * h**2
    if moved <= MARGIN * from_rest + 2 * ENCODER_RESOLUTION:
        return []
    t0 = float(np.asarray(rec.time)[0])
    return [
        f"{where}: {label}: the cart moves at {moved / h:.3g} m/s at the first sample "
        f"(t = {t0:g} s), where the simulations start it at rest: the recording started after "
        "the run did? record from the step, or give initial_velocity [m/s]"
    ]


def check_input_units(rec, plant=None) -> list[str]:
    """An open loop's input u [V] in volts: raises :class:`UserError` when it exceeds what a
    lab amplifier gives (:data:`AMPLIFIER_VOLTAGE`: a column in mV, naming the fix); returns a
    warning when the cart moved far less than the nominal linear cart does under that input
    (:data:`MOTION_FRACTION`), the same sign of other units at a smaller scale."""
    where = str(getattr(rec, "path", "recording"))
    label = _label(rec, "v") if hasattr(rec, "meta") else "the input v"
    u = np.asarray(rec.signal64() if hasattr(rec, "signal64") else rec.experiment.signal, float)
    peak = float(np.max(np.abs(u))) if u.size else 0.0
    if peak > AMPLIFIER_VOLTAGE:
        guess = (
            f"recorded in mV? divide by 1000 for volts ({peak / 1000:.3g} V)"
            if peak / 1000 <= AMPLIFIER_VOLTAGE
            else "not a voltage in V? convert it to volts"
        )
        raise UserError(
            f"{where}: {label}: the input reaches {peak:.4g} V, beyond the {AMPLIFIER_VOLTAGE:g} V "
            f"a lab amplifier gives: {guess} (docs/experiment-files.md: v is in V)"
        )
    plant = rec.plant() if plant is None and hasattr(rec, "plant") else plant
    y = np.asarray(rec.position, dtype=float)
    if plant is None or peak == 0 or y.size < 3:
        return []
    n = min(y.size, u.size, COMMAND_PREFIX)  # the first samples: a bounded cost
    moved = float(np.ptp(y[:n]))
    expected = float(np.ptp(_linear_response(plant, rec.sample_time, u[:n])))
    if moved >= MOTION_FRACTION * expected:
        return []
    return [
        f"{where}: {label}: the cart moves {moved * 1e3:.3g} mm, {moved / expected:.2g} of the "
        f"{expected * 1e3:.3g} mm the nominal cart moves under this input without friction: "
        f"v in mV (divide by 1000), the amplifier off, or the cart blocked?"
    ]


def _linear_response(plant, ts: float, u) -> np.ndarray:
    """Positions [m] of the nominal linear cart m y'' + c y' = gamma u from rest under the
    held input u_k [V] (zero-order hold, exact: :func:`plant_matrices`), for comparing
    magnitudes only."""
    ad, bd = plant_matrices(plant, ts)
    a01, a11, b0, b1 = float(ad[0, 1]), float(ad[1, 1]), float(bd[0]), float(bd[1])
    y = v = 0.0
    out = np.empty(len(u))
    for k, uk in enumerate(np.asarray(u, dtype=float).tolist()):
        out[k] = y
        y, v = y + a01 * v + b0 * uk, a11 * v + b1 * uk
    return out


# ---------------------------------------------------------------- before a fit


def check_fit_recordings(recordings) -> list:
    """The recordings of one fit, as a list, once they make sense together: raises
    :class:`UserError` (one line, naming the recording and the fix) for a recording in which
    the cart does not move, for the same data given twice (the same file, or identical
    samples) and for an open loop's input in other units (:func:`check_input_units`); milder
    doubts are printed once (:func:`warn`). Values the fit returns are checked by the fit."""
    recordings = list(recordings)
    for rec in recordings:
        check_moves(rec)
        if getattr(rec, "kind", None) == "open_loop":
            for message in check_input_units(rec):
                warn(message)
    check_distinct(recordings)
    return recordings


def check_moves(rec, what: str = "nothing to fit") -> None:
    """Raises :class:`UserError` when the cart moves fewer than :data:`MIN_MOTION_COUNTS`
    encoder counts in the whole recording (positions [m])."""
    y = np.asarray(rec.position, dtype=float)
    counts = float(np.ptp(y)) / ENCODER_RESOLUTION if y.size else 0.0
    if counts < MIN_MOTION_COUNTS:
        raise UserError(
            f"{_name(rec)}: the cart does not move: y spans {float(np.ptp(y)) * 1e3:.3g} mm "
            f"({counts:.0f} encoder counts) in the whole recording (amplifier off, motor "
            f"unplugged, cart blocked?); {what}: record a run in which the cart moves"
        )


def check_distinct(recordings) -> None:
    """Raises :class:`UserError` when two recordings are the same file or hold identical
    samples: fitted twice, their standard errors would shrink by sqrt(2) for no new data."""
    seen: dict = {}
    for i, rec in enumerate(recordings):
        path = getattr(rec, "path", None)
        file = Path(path).resolve() if path is not None and Path(path).is_file() else None
        y = np.asarray(rec.position, dtype=float)
        key = (str(getattr(rec, "kind", "")), float(rec.sample_time), y.size)
        for j, (other_file, other_key, other_y, other_signal) in seen.items():
            # One file may hold several runs (a workspace saved after two experiments).
            same_file = file is not None and file == other_file and np.array_equal(y, other_y)
            same_data = key == other_key and np.array_equal(y, other_y)
            same_data = same_data and np.array_equal(_signal(rec), other_signal)
            if same_file or same_data:
                how = "the same file" if same_file else "identical samples"
                raise UserError(
                    f"recordings {j + 1} and {i + 1} are {how} ({_name(recordings[j])}, "
                    f"{_name(rec)}): the same data counted twice would make the standard "
                    f"errors sqrt(2) too small; give each recording once"
                )
        seen[i] = (file, key, y, _signal(rec))


def _signal(rec) -> np.ndarray:
    if hasattr(rec, "signal64"):
        return np.asarray(rec.signal64(), dtype=float)
    return np.asarray(rec.experiment.signal, dtype=float)


def _name(rec) -> str:
    return str(getattr(rec, "path", None) or "recording")


def _check_command(where, label, rec) -> list[str]:
    """The recorded command against the file's controller run on the recorded y and r."""
    pid = rec.controller
    u_rec = np.asarray(rec.command, dtype=float)
    u_calc = controller_command(pid, np.asarray(rec.reference, float), rec.position)
    u_rec = u_rec[: u_calc.size]
    peak = float(np.max(np.abs(u_rec)))
    if not math.isfinite(float(pid.v_limit)) and peak > 0:
        # No software limit in the file: an unlisted amplifier limit shows as a flat top.
        u_calc = np.clip(u_calc, -peak, peak)
    tol = COMMAND_TOL_V + COMMAND_TOL_REL * peak
    best = min(_median_gap(u_rec, u_calc, shift) for shift in (0, 1, -1))
    if best <= tol or not math.isfinite(best):  # not finite: gains beyond range, said above
        return []
    gains = f"kp={float(pid.kp):g} ki={float(pid.ki):g} kd={float(pid.kd):g}"
    # The ratio off the flat top: a clipped command is no multiple of the one computed.
    free = (np.abs(u_rec) < 0.98 * peak) & (np.abs(u_calc) < 0.98 * peak)
    a, b = u_rec[free], u_calc[free]
    scale = float(np.dot(a, b) / np.dot(b, b)) if np.any(b) else 0.0
    hint = ""
    if abs(scale - 1) > 0.1 and scale > 0:
        times = " ".join(f"{k}={scale * float(getattr(pid, k)):.3g}" for k in ("kp", "ki", "kd"))
        hint = f"; the recorded u is about {scale:.3g} times it ({times}?)"
    elif scale < -0.5:
        hint = (
            f"; the recorded u is about {scale:.3g} times it, of the opposite sign: y (and r) "
            "measured the other way along the track (a distance from the far end?) or v of the "
            "other sign; y must grow where a positive voltage drives the cart"
        )
    return [
        f"{where}: {label}: the recorded u is not what {gains} (v_limit {float(pid.v_limit):g} V)"
        f" produce from the recorded y and r (median difference {best:.3g} V{hint}): wrong "
        f"gains or limit in [controller], or v in other units?"
    ]


#: A step is recorded late when the recorded command stays at rest this many samples after
#: t = 0 at least (a sample or two is the loop's own delay, which the command check allows).
LATE_STEP_MIN_SAMPLES = 3


def late_step(rec) -> int | None:
    """The sample at which a closed-loop step really starts, where the file says t = 0 and
    the data say later: ``[reference] kind = "step"``, and the recorded command v stays at the
    rest command (the controller's on r = y, 0 V for P) for the first samples, then follows the
    file's controller stepped there (:func:`controller_command`, within the command check's
    tolerance). None when the step is at t = 0, or when the data say nothing clear (a
    recording that fits neither is left to the command check's warning)."""
    spec = rec.meta.get("reference") if isinstance(rec.meta, dict) else None
    pid, u = rec.controller, rec.command
    if rec.kind != "closed_loop" or pid is None or u is None or not isinstance(spec, dict):
        return None
    if spec.get("kind") != "step":
        return None
    u = np.asarray(u, dtype=float)
    y = np.asarray(rec.position, dtype=float)
    n = min(u.size, COMMAND_PREFIX)
    tol = COMMAND_TOL_V + COMMAND_TOL_REL * float(np.max(np.abs(u[:n])))
    rest = controller_command(pid, y[:n], y[:n])  # nothing to do before the step
    moved = np.nonzero(np.abs(u[:n] - rest) > tol)[0]
    k0 = int(moved[0]) if moved.size else n
    if k0 < LATE_STEP_MIN_SAMPLES or k0 >= n - 1:
        return None
    stepped = np.where(np.arange(n) < k0, y[0], float(np.asarray(rec.reference)[-1]))
    if _median_gap(u[k0:n], controller_command(pid, stepped, y[:n])[k0:], 0) > tol:
        return None
    return k0


def _median_gap(a, b, shift):
    if shift > 0:
        a, b = a[shift:], b[:-shift]
    elif shift < 0:
        a, b = a[:shift], b[-shift:]
    return float(np.median(np.abs(a - b))) if a.size else math.inf


#: The command check looks at the first samples only (the transient, where gains show); the
#: exact loop (anti-windup makes the law nonlinear) at fewer, since it runs in Python.
COMMAND_PREFIX = 100_000
#: Samples x kernel taps up to which the derivative filter is a direct convolution.
DIRECT_CONVOLUTION_LIMIT = 20_000_000
EXACT_PREFIX = 5_000


def controller_command(pid, r, y) -> np.ndarray:
    """The command u_k [V] the canonical PID (:mod:`hw.control_law`) sends for the recorded
    r_k, y_k [m], over the first ``COMMAND_PREFIX`` samples: vectorized when the law is linear
    up to its final clip (no anti-windup), else the exact loop over ``EXACT_PREFIX`` samples.
    The array is that prefix."""
    pid = float_pid(pid)
    r, y = np.asarray(r, float), np.asarray(y, float)
    if pid.anti_windup != "none" and math.isfinite(pid.v_limit):
        n = min(r.size, EXACT_PREFIX)
        state = pid_init(pid, float(r[0]), float(y[0]))
        out = np.empty(n)
        for k in range(n):
            out[k], _, state = pid_update(pid, state, float(r[k]), float(y[k]))
        return out
    r, y = r[:COMMAND_PREFIX], y[:COMMAND_PREFIX]
    ts = pid.sample_time
    e = r - y
    s = e if pid.derivative_on == "error" else -y
    integral = ts * np.concatenate([[0.0], np.cumsum(e[:-1])])
    # d_k = a d_{k-1} + b (s_k - s_{k-1}), d_-1 = 0, s_-1 = s_0: a convolution with b a^j,
    # cut where a^j < 1e-17 (below float64 rounding). Direct for a short kernel, else by FFT
    # (n log n however slow the filter; scipy.signal would cost a second of import).
    a, b = pid.tau / (pid.tau + ts), 1.0 / (pid.tau + ts)
    taps = 1 if a == 0 else min(e.size, int(math.ceil(math.log(1e-17) / math.log(a))) + 1)
    kernel = b * a ** np.arange(taps)
    x = np.diff(s, prepend=s[0])
    if taps * e.size <= DIRECT_CONVOLUTION_LIMIT:
        d = np.convolve(x, kernel)[: e.size]
    else:
        size = 1 << int(e.size + taps - 1).bit_length()
        d = np.fft.irfft(np.fft.rfft(x, size) * np.fft.rfft(kernel, size), size)[: e.size]
    return np.clip(pid.kp * e + pid.ki * integral + pid.kd * d, -pid.v_limit, pid.v_limit)


# ---------------------------------------------------------------- controllers


def plant_matrices(plant, ts):
    """The nominal plant's zero-order-hold discretization (Ad, Bd) for x = [y, y'] [m, m/s]
    and the held voltage [V]: m y'' + c y' = gamma u, effects left out (exact exponential)."""
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    a = c / m
    e = math.exp(-a * ts)
    if a * ts > 1e-8:
        phi1 = (1 - e) / a  # integral of exp(-a s) over [0, ts]
        phi2 = (ts - phi1) / a  # double integral
    else:
        phi1, phi2 = ts - a * ts**2 / 2, ts**2 / 2 - a * ts**3 / 6
    ad = np.array([[1.0, phi1], [0.0, e]])
    bd = (gamma / m) * np.array([phi2, phi1])
    return ad, bd


def plant_delay(plant) -> float:
    """The transport delay of ``plant``'s :class:`~jaxcart.effects.Delay` effect [s] as the
    simulators apply it (clipped to [0, max_delay]); 0 without one. NaN stays NaN."""
    effect = plant.effect(Delay) if hasattr(plant, "effect") else None
    if effect is None:
        return 0.0
    d = float(effect.delay)
    return d if math.isnan(d) else min(max(d, 0.0), float(effect.max_delay))


def delay_split(delay: float, ts: float) -> tuple[int, float]:
    """(n, s) with delay = n Ts + s, 0 <= s < Ts, rounded as :mod:`jaxcart.effects.delay`'s
    exact form does: over [t_k, t_k + s) the motor sees u_{k-n-1}, then u_{k-n}."""
    n = int(math.floor(delay / ts))
    split = delay - n * ts
    if split >= ts:  # rounding at a whole number of samples
        n, split = n + 1, 0.0
    return n, split


def delayed_plant(plant, ts: float, delay: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the zero-order-hold cart behind a transport ``delay`` [s], exactly:
    x_{k+1} = A x_k + B u_k with x = [y, y', u_{k-1}, ..., u_{k-L}] [m, m/s, V...]. With
    delay = n Ts + s (:func:`delay_split`) the motor sees u_{k-n-1} over the first s of the
    sample and u_{k-n} over the rest (the split-hold, modified-z discretization:
    y_{k+1} = Ad x_k + G_late u_{k-n} + G_early u_{k-n-1}, G_late the hold over Ts - s, G_early
    = e^{A (Ts - s)} times the hold over s); L = n, or n + 1 for a split sample. Shared by
    :func:`closed_loop_matrix` and :func:`jaxcart.control_systems.plant_ss`."""
    ad, bd = plant_matrices(plant, ts)
    n, split = delay_split(delay, ts) if delay else (0, 0.0)
    length = n + 1 if split > 0 else n
    size = 2 + length
    a, b = np.zeros((size, size)), np.zeros(size)
    a[:2, :2] = ad
    if length == 0:
        b[:2] = bd
        return a, b
    phi_late, g_late = plant_matrices(plant, ts - split)
    g_early = phi_late @ plant_matrices(plant, split)[1]
    for lag, gain in ((n, g_late), (n + 1, g_early)):
        if lag == 0:
            b[:2] += gain
        elif lag <= length:
            a[:2, 1 + lag] += gain  # u_{k-lag} is state 1 + lag
    b[2] = 1.0  # u_{k-1} <- u_k
    for j in range(1, length):
        a[2 + j, 1 + j] = 1.0  # u_{k-j-1} <- u_{k-j}
    return a, b


def closed_loop_matrix(pid, plant, *, with_delay: bool = True) -> np.ndarray:
    """The matrix of the discrete closed loop (r = 0, no limit): state [y, y', I, d_{k-1},
    s_{k-1}] of the plant and the canonical PID (derivative on error and on measurement have
    the same loop when r = 0), 5 x 5; with a ``delay`` effect, delay = n Ts + s
    (:func:`delay_split`), the past commands u_{k-1} ... u_{k-L} follow (L = n, or n + 1 for a
    split sample), and the cart is the modified-z (split-hold) discretization
    x_{k+1} = Ad x_k + G_late u_{k-n} + G_early u_{k-n-1}: G_late the hold over the last
    Ts - s of the sample, G_early = e^{A (Ts - s)} times the hold over the first s.
    ``with_delay=False``: the 5 x 5 loop without the delay."""
    ts = float(pid.sample_time)
    kp, ki, kd, tau = (float(pid.kp), float(pid.ki), float(pid.kd), float(pid.tau))
    delay = plant_delay(plant) if with_delay else 0.0
    if not math.isfinite(delay):
        raise ValueError(f"plant delay = {delay!r} s: give a finite number of seconds")
    pa, pb = delayed_plant(plant, ts, delay)
    size = 3 + pa.shape[0]
    # The plant's states [y, y', delay line] in the loop's order [y, y', I, d, s, delay line].
    at = np.r_[0, 1, 5:size]
    cy = np.eye(size)[0]  # y_k
    # d_k = (tau d_{k-1} + s_k - s_{k-1}) / (tau + Ts), s_k = e_k = -y_k
    d_row = np.zeros(size)
    d_row[:5] = np.array([-1.0, 0.0, 0.0, tau, -1.0]) / (tau + ts)
    u_row = -kp * cy + ki * np.eye(size)[2] + kd * d_row  # u_k
    a = np.zeros((size, size))
    a[np.ix_(at, at)] = pa
    a[at] += np.outer(pb, u_row)
    a[2] = np.eye(size)[2] - ts * cy
    a[3] = d_row
    a[4] = -cy
    return a


def closed_loop_eigenvalues(pid, plant, *, with_delay: bool = True) -> np.ndarray:
    """Eigenvalues of :func:`closed_loop_matrix` (discrete time, |z| < 1 stable); all inf
    when gains beyond float range (1e308) make the matrix overflow."""
    with np.errstate(over="ignore", invalid="ignore"):
        a = closed_loop_matrix(pid, plant, with_delay=with_delay)
    if not np.all(np.isfinite(a)):
        return np.full(a.shape[0], np.inf + 0j)
    return np.linalg.eigvals(a)


def check_controller(pid, plant, *, where: str = "controller") -> list[str]:
    """Warnings (strings) for an unstable or implausible PID on ``plant``'s linear part (its
    m, c, gamma and its transport delay; other effects left out)."""
    gains = f"kp={float(pid.kp):g} ki={float(pid.ki):g} kd={float(pid.kd):g}"
    if not all(math.isfinite(float(getattr(pid, k))) for k in ("kp", "ki", "kd", "tau")):
        return [f"{where}: {gains}: not finite"]
    delay = plant_delay(plant)
    if not math.isfinite(delay):
        return [f"{where}: the plant's delay = {delay!r} s is not finite"]
    z = closed_loop_eigenvalues(pid, plant)
    if not np.all(np.isfinite(z)):
        return [f"{where}: {gains}: gains beyond any cart (the loop overflows float64)"]
    out = []
    for k in ("kp", "ki", "kd"):  # stable or not, a negative gain is a sign error
        problem = setting_problem(k, float(getattr(pid, k)))
        if problem is not None:
            out.append(f"{where}: {k} = {problem}")
    worst = z[np.argmax(np.abs(z))]
    if abs(worst) > 1 + UNIT_CIRCLE_TOL:
        behind = f" with its {delay * 1e3:.4g} ms delay" if delay else ""
        out.append(
            f"{where}: {gains} make the loop unstable on the nominal plant{behind} (discrete "
            f"eigenvalue {_complex(worst)}, |z| = {abs(worst):.6g} > 1): the cart runs away, or "
            f"oscillates where a voltage limit holds it; check the gains' signs and sizes"
            + (" and the delay" if delay else "")
        )
    volts = float(voltage_limit(plant, pid))
    volts = volts if math.isfinite(volts) else LAB_VOLTAGE
    q = ENCODER_RESOLUTION
    kp, kd, ts = abs(float(pid.kp)), abs(float(pid.kd)), float(pid.sample_time)
    if kp * q > volts:
        out.append(
            f"{where}: kp={float(pid.kp):g} V/m is implausible: one encoder count ({q:g} m) "
            f"already asks {kp * q:.3g} V, beyond the {volts:g} V range, so the loop acts as a "
            f"relay; the lab's gains are 10-250 V/m"
        )
    if kd * q / (float(pid.tau) + ts) > volts:
        out.append(
            f"{where}: kd={float(pid.kd):g} V s/m is implausible with tau = {float(pid.tau):g} s:"
            f" one encoder count swings the derivative term by "
            f"{kd * q / (float(pid.tau) + ts):.3g} V, beyond the {volts:g} V range"
        )
    # Fast modes judge the gains, on the loop without the delay: a delay line's own poles
    # (|z| ~ 0.5-0.8 at every angle for a 10-25 ms delay) are no sign of implausible gains.
    if delay:
        z = closed_loop_eigenvalues(pid, plant, with_delay=False)
        if not np.all(np.isfinite(z)) or np.max(np.abs(z)) > 1 + UNIT_CIRCLE_TOL:
            return out
    fast = z[(np.abs(z) > 0.5) & (np.abs(np.angle(z)) > 2 * math.pi * MAX_MODE_FRACTION)]
    if fast.size and abs(worst) <= 1 + UNIT_CIRCLE_TOL:
        f_mode = float(np.max(np.abs(np.angle(fast)))) / (2 * math.pi * ts)
        out.append(
            f"{where}: {gains} give a closed-loop mode at {f_mode:.0f} Hz, beyond what the "
            f"{1 / ts:g} Hz loop resolves ({MAX_MODE_FRACTION / ts:g} Hz): implausible gains"
        )
    return out


def _complex(z) -> str:
    z = complex(z)
    if abs(z.imag) < 1e-12 * max(1.0, abs(z)):
        return f"{z.real:.5g}"
    return f"{z.real:.5g} {'+' if z.imag >= 0 else '-'} j{abs(z.imag):.5g}"


def check_track(response, where: str) -> list[str]:
    """A warning when a simulated cart leaves the track: |y - y0| beyond the travel [m]."""
    y = np.asarray(response.position, dtype=float)
    if y.ndim != 1 or y.size == 0:
        return []
    excursion = float(np.max(np.abs(y - y[0])))
    if excursion <= TRAVEL:
        return []
    k = int(np.argmax(np.abs(y - y[0]) > TRAVEL))
    t = float(np.asarray(response.time)[k])
    return [
        f"{where}: the simulated cart leaves the track: |y - y0| reaches {excursion:.3g} m "
        f"(beyond the {TRAVEL} m travel from t = {t:.3g} s); the real cart would hit the end "
        f"stop"
    ]
