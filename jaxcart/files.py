"""Experiment files, the project's exchange format: one TOML file per experiment, data in CSV or
MATLAB .mat (DESIGN.md, "Experiment files").

    kind = "closed_loop"              # "tap" | "open_loop" | "closed_loop"
    sample_time = 0.001               # [s]
    data = "run.csv"                  # header t, y and optionally v, r, e ([s], [m], [V], [m])
    # or a table:  [data]  y = "2.1pos.mat:y"   v = "2.1volt.mat:v"   (or "run.csv:column")
    [controller]  kp = 50.0  ki  kd  tau  kb  derivative_on  anti_windup  v_limit
    [reference]   kind = "step", amplitude = 0.4  |  "ramp", slope  |  "column" (column r)
    [input]       open loop: kind = "step", amplitude [V] | "ramp", slope [V/s] | "column" (v)
    [tap]         motor_connected = false
    [plant]       overrides of the handout's parameters by name, e.g. M = 1.25, f_c = 0.3
    description = "..."   initial_velocity = 0.0 [m/s]   [notes] free-form provenance

Every problem is a :class:`UserError` with one line naming the file, the field and what to do.

>>> rec = read_experiment("../shared/realdata/p50.toml")          # doctest: +SKIP
>>> rec.kind, rec.position.shape, rec.controller.kp                # doctest: +SKIP
('closed_loop', (2705,), 50.0)
"""

from __future__ import annotations

import csv
import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from hw.control_law import ANTI_WINDUP_MODES, DERIVATIVE_MODES, PID
from jaxcart import effects as _effects
from jaxcart.errors import UserError
from jaxcart.experiments import KINDS, Experiment
from jaxcart.params import Plant, handout_plant, tap_plant

COLUMNS = ("t", "y", "v", "r", "e")
COLUMN_UNITS = {"t": "s", "y": "m", "v": "V", "r": "m", "e": "m"}
TOP_KEYS = (
    "kind",
    "sample_time",
    "description",
    "initial_velocity",
    "data",
    "controller",
    "reference",
    "input",
    "tap",
    "plant",
    "notes",
)
CONTROLLER_KEYS = ("kp", "ki", "kd", "tau", "kb", "v_limit", "derivative_on", "anti_windup")
#: Keys of [reference] and [input] for each of their kinds (besides "kind").
SIGNAL_KEYS = {"step": ("amplitude",), "ramp": ("slope",), "column": ()}
TAP_KEYS = ("motor_connected",)
#: Allowed time-step deviation from sample_time (DESIGN: more than 1 % off is an error).
TIME_TOLERANCE = 0.01
# Plant parameters that must be > 0 (divisors or a mass) and those that must be >= 0.
_POSITIVE = ("M", "Rm", "Kg", "r_mp", "eta_g", "eta_m", "v_sat")
_NONNEGATIVE = ("B_eq", "Kt", "Km", "Jm", "gamma_scale", "f_c")
_MAY_BE_INF = ("v_sat",)


@dataclass(frozen=True, eq=False)
class Recording:
    """One experiment read from its TOML file (arrays are numpy float64).

    path: the TOML file; kind: "tap" | "open_loop" | "closed_loop"; sample_time: Ts [s]
    time: sample times [s] as recorded; position: y [m]
    command: v, the voltage the software sent [V], or None (no column v)
    reference: r [m] for closed loop (from [reference]), else None
    controller: the PID that ran (from [controller]), or None
    plant_overrides: [plant] as {name: value} (SI units)
    experiment: the same samples as an :class:`Experiment` (t = k Ts from 0, y0 = first
        position), ready for :func:`jaxcart.simulate`
    meta: the parsed TOML
    """

    path: Path
    kind: str
    sample_time: float
    time: np.ndarray
    position: np.ndarray
    command: np.ndarray | None
    reference: np.ndarray | None
    controller: PID | None
    plant_overrides: dict
    experiment: Experiment
    meta: dict

    @property
    def n_samples(self) -> int:
        return int(self.position.shape[0])

    def as_response(self):
        """The recording as a :class:`jaxcart.Response` (numpy arrays), for step_info and plots:
        velocity by central differences [m/s]; reference r (or y0 when there is none); command
        and voltage both the recorded v (zeros without a column v)."""
        from jaxcart.simulate import Response

        y = self.position
        r = self.reference if self.reference is not None else np.full(y.shape, y[0])
        v = self.command if self.command is not None else np.zeros(y.shape)
        values = dict(
            time=self.time,
            position=y,
            velocity=np.gradient(y, self.time),
            reference=r,
            error=r - y,
            command=v,
            voltage=v,
            diverged=np.asarray(False),
            kind=self.kind,
        )
        names = {f.name for f in dataclasses.fields(Response)}
        return Response(**{k: val for k, val in values.items() if k in names})

    def plant(self, base: Plant | None = None) -> Plant:
        """The plant this experiment ran on: ``base`` (default: the handout's plant, or the
        motor-unplugged :func:`jaxcart.tap_plant` for a tap) with [plant] applied."""
        if base is None:
            base = default_base(self.kind, self.meta)
        return plant_from_overrides(self.plant_overrides, base, where=f"{self.path} [plant]")

    def experiment_for(self, horizon: float) -> Experiment:
        """The experiment over ``horizon`` [s] instead of the recording's length: step and ramp
        signals are continued exactly, column signals hold their last value."""
        if not (math.isfinite(horizon) and horizon > 0):
            raise UserError(f"horizon = {horizon!r} s: give a positive number of seconds")
        ts = self.sample_time
        n = int(round(horizon / ts)) + 1
        exp = self.experiment
        spec = self.meta.get("reference" if self.kind == "closed_loop" else "input", {})
        k = np.arange(n)
        signal = np.asarray(exp.signal, dtype=float)
        if self.kind == "tap":
            new = np.zeros(n)
        elif spec.get("kind") == "ramp":
            offset = exp.y0 if self.kind == "closed_loop" else 0.0
            new = offset + float(spec["slope"]) * k * ts
        elif n <= signal.size:
            new = signal[:n]
        else:
            new = np.concatenate([signal, np.full(n - signal.size, signal[-1])])
        return dataclasses.replace(exp, signal=jnp.asarray(new))


# ---------------------------------------------------------------- reading


def read_experiment(path) -> Recording:
    """Read an experiment file (TOML + CSV/.mat data); see the module docstring for the format.

    Relative data paths are relative to the TOML file's folder. Raises :class:`UserError` with a
    one-line message for any problem in the file or its data.
    """
    path = Path(path)
    if path.is_dir():
        raise UserError(f"experiment file {path} is a folder; give the path of a .toml file")
    if not path.is_file():
        raise UserError(f"experiment file {path} not found; give the path of a .toml file")
    try:
        with path.open("rb") as f:
            meta = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({_one_line(exc)}); fix the syntax") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read it ({_one_line(exc)})") from None
    return _Reader(path, meta).recording()


class _Signal:
    """One data column: values, its own time vector (or None) and how to name its rows."""

    def __init__(self, values, time, label, row):
        self.values, self.time, self.label, self.row = values, time, label, row


class _Reader:
    def __init__(self, path: Path, meta: dict):
        self.path, self.meta, self.folder = path, meta, path.parent
        self._csv_cache: dict = {}
        self._mat_cache: dict = {}

    def fail(self, message: str):
        raise UserError(f"{self.path}: {message}")

    # -- values

    def number(self, value, field, *, positive=False, nonnegative=False, allow_inf=False):
        if isinstance(value, bool) or not isinstance(value, int | float):
            self.fail(f"{field} = {value!r}: give a number")
        value = float(value)
        if math.isnan(value) or (math.isinf(value) and not allow_inf):
            self.fail(f"{field} = {value!r}: give a finite number")
        if positive and not value > 0:
            self.fail(f"{field} = {value!r}: it must be positive")
        if nonnegative and not value >= 0:
            self.fail(f"{field} = {value!r}: it must be >= 0")
        return value

    def choice(self, value, field, allowed):
        if value not in allowed:
            self.fail(f"{field} = {value!r}: use one of {', '.join(map(repr, allowed))}")
        return value

    def table(self, name, allowed):
        table = self.meta.get(name, {})
        if not isinstance(table, dict):
            self.fail(f"{name} = {table!r}: it must be a table [{name}]")
        for key in table:
            if key not in allowed:
                self.fail(f"unknown key {key!r} in [{name}]; allowed: {', '.join(allowed)}")
        return table

    # -- the file

    def recording(self) -> Recording:
        meta = self.meta
        for key in meta:
            if key not in TOP_KEYS:
                self.fail(f"unknown key {key!r}; allowed keys: {', '.join(TOP_KEYS)}")
        if "kind" not in meta:
            self.fail(f"no kind; add kind = one of {', '.join(map(repr, KINDS))}")
        kind = self.choice(meta["kind"], "kind", KINDS)
        if "description" in meta and not isinstance(meta["description"], str):
            self.fail(f"description = {meta['description']!r}: give a string")
        if "notes" in meta and not isinstance(meta["notes"], dict):
            self.fail("notes must be a table [notes]")
        yd0 = self.number(meta.get("initial_velocity", 0.0), "initial_velocity")
        for section, owner in (
            ("controller", "closed_loop"),
            ("reference", "closed_loop"),
            ("input", "open_loop"),
            ("tap", "tap"),
        ):
            if section in meta and kind != owner:
                self.fail(
                    f"[{section}] belongs to kind = {owner!r}, this file is {kind!r}; "
                    f"remove it or change kind"
                )

        signals = self.signals()
        time, ts = self.time(signals)
        n = time.size
        position = signals["y"].values
        command = signals["v"].values if "v" in signals else None
        y0 = float(position[0])
        k = np.arange(n)
        controller = reference = None
        if kind == "closed_loop":
            controller = self.controller(ts)
            spec = self.signal_spec("reference", "r", signals)
            reference = self.signal_from_spec(spec, "reference", "r", signals, k * ts, y0)
            signal = reference
        elif kind == "open_loop":
            spec = self.signal_spec("input", "v", signals)
            signal = self.signal_from_spec(spec, "input", "v", signals, k * ts, 0.0)
        else:
            tap = self.table("tap", TAP_KEYS)
            if not isinstance(tap.get("motor_connected", False), bool):
                self.fail(f"[tap] motor_connected = {tap['motor_connected']!r}: give true or false")
            signal = np.zeros(n)
        overrides = self.plant_overrides()
        experiment = Experiment(jnp.asarray(signal), y0=y0, yd0=yd0, kind=kind, sample_time=ts)
        return Recording(
            path=self.path,
            kind=kind,
            sample_time=ts,
            time=time,
            position=position,
            command=command,
            reference=reference,
            controller=controller,
            plant_overrides=overrides,
            experiment=experiment,
            meta=meta,
        )

    # -- data

    def signals(self) -> dict[str, _Signal]:
        data = self.meta.get("data")
        if data is None:
            self.fail('no data; add data = "run.csv" or a [data] table (y = "file.mat:variable")')
        if isinstance(data, str):
            if data.lower().endswith(".mat"):
                self.fail(
                    f"data = {data!r}: map each signal of a .mat file in a [data] table, "
                    f'e.g. [data] y = "{data}:variable"'
                )
            header, columns, lines = self.read_csv(data, "data")
            unknown = [name for name in header if name not in COLUMNS]
            for required in ("t", "y"):
                if required not in columns:
                    guess = unknown[0] if unknown else "column"
                    self.fail(
                        f"column {required!r} missing in {data} (columns: "
                        f"{', '.join(header)}); name the {_LONG[required]} column "
                        f"{required} or map it in a [data] table ({required} = "
                        f'"{data}:{guess}")'
                    )
            if unknown:
                self.fail(
                    f"column {unknown[0]!r} of {data} is not one of {', '.join(COLUMNS)}; "
                    f"rename it, or map the columns you need in a [data] table "
                    f'(e.g. y = "{data}:y", v = "{data}:{unknown[0]}")'
                )
            return {
                name: _Signal(values, None, f"{data} column {name}", _line_of(lines))
                for name, values in columns.items()
            }
        if not isinstance(data, dict):
            self.fail(f"data = {data!r}: give a CSV file name or a [data] table")
        for key in data:
            if key not in COLUMNS:
                self.fail(
                    f"unknown key {key!r} in [data]; allowed: {', '.join(COLUMNS)} "
                    f"({', '.join(f'{c} [{u}]' for c, u in COLUMN_UNITS.items())})"
                )
        if "y" not in data:
            self.fail('[data] has no y; map the position [m]: y = "file.mat:variable"')
        return {name: self.mapped(name, source) for name, source in data.items()}

    def mapped(self, name, source) -> _Signal:
        field = f"[data] {name}"
        if not isinstance(source, str) or ":" not in source:
            self.fail(f'{field} = {source!r}: give "file.mat:variable" or "file.csv:column"')
        file, variable = source.rsplit(":", 1)
        if file.lower().endswith(".mat"):
            values, time = self.read_mat(file, variable, field)
            return _Signal(values, time, source, lambda i: f"row {i + 1}")
        if file.lower().endswith((".csv", ".txt")):
            header, columns, lines = self.read_csv(file, field)
            if variable not in columns:
                self.fail(
                    f"{field}: column {variable!r} missing in {file} (columns: "
                    f"{', '.join(header)}); map one of them"
                )
            return _Signal(columns[variable], None, source, _line_of(lines))
        self.fail(f"{field} = {source!r}: the file must be .mat or .csv")

    def data_path(self, name, field) -> Path:
        path = self.folder / name
        if not path.is_file():
            self.fail(
                f"{field}: data file {name} not found (looked for {path}); "
                f"fix the path (relative to the TOML file's folder)"
            )
        return path

    def read_csv(self, name, field):
        if name in self._csv_cache:
            return self._csv_cache[name]
        path = self.data_path(name, field)
        header, rows, lines = None, [], []
        try:
            with path.open(newline="") as f:
                for lineno, row in enumerate(csv.reader(f), start=1):
                    if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                        continue
                    if header is None:
                        header = [h.strip() for h in row]
                        continue
                    if len(row) != len(header):
                        self.fail(
                            f"{name} line {lineno}: {len(row)} fields, the header has "
                            f"{len(header)}; fix that line"
                        )
                    try:
                        rows.append([float(x) for x in row])
                    except ValueError:
                        bad = next(x for x in row if not _is_float(x))
                        col = header[row.index(bad)]
                        self.fail(
                            f"{name} line {lineno}, column {col}: {bad.strip()!r} is not "
                            f"a number; fix that value"
                        )
                    lines.append(lineno)
        except (OSError, UnicodeDecodeError) as exc:
            self.fail(f"{field}: cannot read {name} ({_one_line(exc)})")
        if header is None or not rows:
            self.fail(f"{field}: {name} has no data rows; it needs a header line and samples")
        if len(set(header)) != len(header):
            self.fail(f"{name}: repeated column names in the header {header}; name each once")
        table = np.asarray(rows, dtype=float)
        result = header, {h: table[:, i] for i, h in enumerate(header)}, np.asarray(lines)
        self._csv_cache[name] = result
        return result

    def read_mat(self, name, variable, field):
        path = self.data_path(name, field)
        if name not in self._mat_cache:
            import scipy.io

            try:
                self._mat_cache[name] = scipy.io.loadmat(
                    path, squeeze_me=True, struct_as_record=False
                )
            except NotImplementedError:
                self.fail(
                    f"{field}: {name} is a MATLAB v7.3 file; save it with "
                    f"save('{name}', ..., '-v7') so it can be read"
                )
            except Exception as exc:  # scipy raises several kinds for a broken file
                self.fail(f"{field}: cannot read {name} as a .mat file ({_one_line(exc)})")
        mat = self._mat_cache[name]
        names = [k for k in mat if not k.startswith("__")]
        if variable not in names:
            self.fail(
                f"{field}: variable {variable!r} not in {name} (variables: "
                f"{', '.join(names) or 'none'}); map one of them"
            )
        return self.mat_signal(mat[variable], f"{name}:{variable}", field)

    def mat_signal(self, obj, label, field):
        """Values and time (or None) of one .mat variable in a Simulink scope layout."""
        from scipy.io.matlab import mat_struct

        time = None
        if isinstance(obj, mat_struct):
            names = list(getattr(obj, "_fieldnames", []))
            if "signals" not in names:
                self.fail(
                    f"{field}: {label} is a structure without signals (fields: "
                    f"{', '.join(names)}); save the scope as 'Structure With Time'"
                )
            signals = obj.signals
            if not isinstance(signals, mat_struct):
                self.fail(f"{field}: {label} holds several signals; save one signal per variable")
            values = _numeric(signals.values)
            if values is None or values.ndim != 1:
                self.fail(
                    f"{field}: {label}.signals.values is not one column of numbers "
                    f"(shape {np.shape(signals.values)}); save one signal per variable"
                )
            raw_time = _numeric(getattr(obj, "time", None))
            if raw_time is not None and raw_time.size:
                time = raw_time.ravel()
                if time.size != values.size:
                    self.fail(
                        f"{field}: {label}.time has {time.size} samples, its values "
                        f"{values.size}; save the scope again"
                    )
            return values, time
        values = _numeric(obj)
        if values is None:
            self.fail(
                f"{field}: {label} is not numeric (a {type(obj).__name__}); give an N x 2 "
                f"array [t, value], a vector or a Simulink scope structure"
            )
        if values.ndim == 2 and values.shape[1] != 2 and values.shape[0] == 2:
            values = values.T  # MATLAB's 2 x N row form
        if values.ndim == 2 and values.shape[1] == 2:
            return values[:, 1].copy(), values[:, 0].copy()
        if values.ndim != 1 or values.size < 2:
            self.fail(
                f"{field}: {label} has shape {values.shape}; give an N x 2 array "
                f"[t, value], a vector or a Simulink scope structure"
            )
        return values, time

    def time(self, signals):
        """The time vector [s] and the sample time [s], after every consistency check."""
        sizes = {name: s.values.size for name, s in signals.items()}
        if len(set(sizes.values())) > 1:
            listing = ", ".join(f"{n} ({signals[n].label}) {sizes[n]}" for n in sizes)
            self.fail(f"data lengths differ: {listing} samples; give every signal the same samples")
        n = sizes["y"]
        if n < 2:
            self.fail(f"{signals['y'].label}: {n} sample(s); a recording needs at least 2")
        for s in signals.values():
            for what, values in (("", s.values), (" time", s.time)):
                if values is None:
                    continue
                bad = np.nonzero(~np.isfinite(values))[0]
                if bad.size:
                    self.fail(
                        f"{s.label}{what}: {float(values[bad[0]])!r} at {s.row(bad[0])} "
                        f"({bad.size} non-finite samples); remove or fill them"
                    )
        if "t" in signals:
            source = signals["t"]
            time = source.values
        else:
            timed = [s for name, s in signals.items() if s.time is not None]
            source = timed[0] if timed else None
            time = source.time if source else None
            for other in timed[1:]:
                gap = np.abs(other.time - time).max()
                if gap > 0.5 * _median_step(time):
                    self.fail(
                        f"time vectors of {source.label} and {other.label} differ by "
                        f"{gap:.3g} s; give signals sampled at the same times"
                    )
        ts = self.meta.get("sample_time")
        if ts is not None:
            ts = self.number(ts, "sample_time", positive=True)
        if time is None:
            if ts is None:
                self.fail(
                    "no time vector in the data and no sample_time; add sample_time = "
                    "0.001 (s) or a time column t"
                )
            return np.arange(n) * ts, ts
        steps = np.diff(time)
        back = np.nonzero(steps <= 0)[0]
        if back.size:
            i = back[0] + 1
            self.fail(
                f"time of {source.label} does not increase at {source.row(i)} "
                f"(t = {float(time[i - 1])!r} then {float(time[i])!r} s); sort the samples or "
                f"remove repeated rows"
            )
        if ts is None:
            ts = float(f"{(time[-1] - time[0]) / (n - 1):.12g}")
            where = f"the mean step of {source.label}"
        else:
            where = f"sample_time = {ts!r} s"
        off = np.nonzero(np.abs(steps - ts) > TIME_TOLERANCE * ts)[0]
        if off.size:
            i = off[0] + 1
            self.fail(
                f"time of {source.label} steps by {steps[off[0]]:.6g} s at {source.row(i)}, "
                f"more than 1 % from {where}; fix sample_time or resample the data to a "
                f"uniform step"
            )
        return time, ts

    # -- sections

    def controller(self, ts) -> PID | None:
        if "controller" not in self.meta:
            return None
        table = self.table("controller", CONTROLLER_KEYS)
        field = "[controller] {}".format
        values = {}
        for key in ("kp", "ki", "kd"):
            values[key] = self.number(table.get(key, 0.0), field(key))
        values["tau"] = self.number(table.get("tau", 0.01), field("tau"), nonnegative=True)
        values["kb"] = self.number(table.get("kb", 1.0), field("kb"), nonnegative=True)
        values["v_limit"] = self.number(
            table.get("v_limit", math.inf), field("v_limit"), positive=True, allow_inf=True
        )
        values["derivative_on"] = self.choice(
            table.get("derivative_on", "error"), field("derivative_on"), DERIVATIVE_MODES
        )
        values["anti_windup"] = self.choice(
            table.get("anti_windup", "none"), field("anti_windup"), ANTI_WINDUP_MODES
        )
        return PID(sample_time=ts, **values)

    def signal_spec(self, section, column, signals) -> dict:
        """[reference] or [input] as a dict with its kind; defaults to the column if present."""
        if section not in self.meta:
            if column in signals:
                return {"kind": "column"}
            what = "reference [m]" if section == "reference" else "voltage input [V]"
            self.fail(
                f"no [{section}] and no column {column}; add [{section}] kind = "
                f'"step" with amplitude, "ramp" with slope, or a column {column} '
                f"(the {what})"
            )
        table = self.meta[section]
        if not isinstance(table, dict):
            self.fail(f"{section} = {table!r}: it must be a table [{section}]")
        kind = self.choice(table.get("kind"), f"[{section}] kind", tuple(SIGNAL_KEYS))
        allowed = ("kind",) + SIGNAL_KEYS[kind]
        for key in table:
            if key not in allowed:
                self.fail(
                    f"unknown key {key!r} in [{section}] (kind = {kind!r}); allowed: "
                    f"{', '.join(allowed)}"
                )
        for key in SIGNAL_KEYS[kind]:
            if key not in table:
                self.fail(f"[{section}] kind = {kind!r} needs {key}; add {key} = ...")
            self.number(table[key], f"[{section}] {key}")
        if kind == "column" and column not in signals:
            self.fail(
                f"[{section}] kind = 'column' but the data have no column {column}; add "
                f"it to the data or map it in [data]"
            )
        return table

    def signal_from_spec(self, spec, section, column, signals, t, offset):
        kind = spec["kind"]
        if kind == "column":
            return signals[column].values
        if kind == "step":
            return np.full(t.shape, float(spec["amplitude"]))
        return offset + float(spec["slope"]) * t

    def plant_overrides(self) -> dict:
        table = self.meta.get("plant", {})
        if not isinstance(table, dict):
            self.fail(f"plant = {table!r}: it must be a table [plant]")
        return check_plant_overrides(table, f"{self.path} [plant]")


_LONG = {
    "t": "time [s]",
    "y": "position [m]",
    "v": "voltage [V]",
    "r": "reference [m]",
    "e": "error [m]",
}


def _line_of(lines):
    return lambda i: f"line {int(lines[i])}"


def _is_float(text) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _numeric(obj):
    """obj as a 1-D or 2-D float64 array (squeezed), or None if it is not numeric."""
    if obj is None:
        return None
    arr = np.asarray(obj)
    if arr.dtype.kind not in "biuf":
        return None
    arr = np.squeeze(arr.astype(float))
    return arr.reshape(1) if arr.ndim == 0 else arr


def _median_step(time):
    return float(np.median(np.diff(time))) if time.size > 1 else 0.0


def _one_line(exc) -> str:
    return " ".join(str(exc).split())


# ---------------------------------------------------------------- plants


def _effect_classes():
    """Effect classes of :mod:`jaxcart.effects` by parameter name (new effects join here)."""
    found = {}
    for name in getattr(_effects, "__all__", ()):
        cls = getattr(_effects, name, None)
        if isinstance(cls, type) and issubclass(cls, _effects.Effect):
            for param in cls.param_names:
                found.setdefault(param, cls)
    return found


def plant_parameter_names() -> tuple[str, ...]:
    """Names allowed in [plant]: the plant's own parameters and every effect's parameters."""
    own = Plant(effects=()).param_names()
    return own + tuple(p for p in _effect_classes() if p not in own)


def check_plant_overrides(overrides, where: str = "plant overrides") -> dict:
    """Validated {name: float} of plant overrides; ``where`` names the source in errors."""
    allowed = plant_parameter_names()
    checked = {}
    for name, value in dict(overrides).items():
        if name not in allowed:
            raise UserError(
                f"{where}: unknown plant parameter {name!r}; known: {', '.join(allowed)}"
            )
        if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
            raise UserError(f"{where}: {name} = {value!r}: give a number (SI units)")
        value = float(value)
        if math.isnan(value) or (math.isinf(value) and name not in _MAY_BE_INF):
            raise UserError(f"{where}: {name} = {value!r}: give a finite number")
        if name in _POSITIVE and not value > 0:
            unit = "the cart needs a positive mass" if name == "M" else "it must be positive"
            raise UserError(f"{where}: {name} = {value!r}: {unit}")
        if name in _NONNEGATIVE and not value >= 0:
            raise UserError(f"{where}: {name} = {value!r}: it must be >= 0")
        checked[name] = value
    return checked


def default_base(kind: str, meta: dict | None = None) -> Plant:
    """The nominal plant of an experiment kind: the handout's, or the unplugged motor of a tap."""
    if kind == "tap" and not (meta or {}).get("tap", {}).get("motor_connected", False):
        return tap_plant()
    return handout_plant()


def plant_from_overrides(overrides, base: Plant | None = None, *, where="plant overrides"):
    """``base`` (default :func:`jaxcart.handout_plant`) with named parameters replaced.

    Names are the plant's (``M``, ``B_eq``, ...) or an effect's; an effect parameter the base
    lacks adds that effect (``f_c`` adds Coulomb friction, ``v_sat`` a saturation) unless every
    value given for it is 0.
    """
    base = handout_plant() if base is None else base
    values = check_plant_overrides(overrides, where)
    present = set(base.param_names())
    own = {k: v for k, v in values.items() if k in present}
    added: dict[type, dict] = {}
    classes = _effect_classes()
    for name, value in values.items():
        if name not in present:
            added.setdefault(classes[name], {})[name] = value
    try:
        plant = base.replace(**own)
        extra = tuple(cls(**p) for cls, p in added.items() if any(v != 0 for v in p.values()))
        return dataclasses.replace(plant, effects=tuple(plant.effects) + extra)
    except (ValueError, TypeError, KeyError) as exc:
        raise UserError(f"{where}: {_one_line(exc)}") from None


# ---------------------------------------------------------------- writing


def write_experiment(
    toml_path,
    response,
    *,
    controller: PID | None = None,
    plant_overrides: dict | None = None,
    description: str | None = None,
    force: bool = False,
) -> Path:
    """Write a :class:`jaxcart.Response` as an experiment file: ``name.toml`` and ``name.csv``.

    Columns: t [s], y [m], v [V] (the command the software sent), and for closed loop r, e [m];
    every value with 17 significant digits (exact round trip). The reference (or open-loop
    input) is recorded as a column. ``controller`` and ``plant_overrides`` go to [controller]
    and [plant]. Refuses to overwrite either file unless ``force``. Returns the TOML path.
    """
    toml_path, csv_path = experiment_paths(Path(toml_path))
    for path in (toml_path, csv_path):
        if path.exists() and not force:
            raise UserError(
                f"{path} exists; choose another name or pass --force (force=True) to overwrite it"
            )
    kind = response.kind
    arrays = {
        "t": response.time,
        "y": response.position,
        "v": response.command,
        "r": response.reference,
        "e": response.error,
    }
    names = {"closed_loop": COLUMNS, "open_loop": ("t", "y", "v"), "tap": ("t", "y")}[kind]
    columns = {name: np.asarray(arrays[name], dtype=float) for name in names}
    n = columns["t"].shape[-1]
    if any(c.ndim != 1 for c in columns.values()):
        raise UserError(
            f"{toml_path}: the response holds a batch of runs "
            f"(shape {columns['y'].shape}); write one run at a time"
        )
    if bool(np.any(np.asarray(response.diverged))):
        raise UserError(f"{toml_path}: the simulated run diverged; nothing written")
    for name, values in columns.items():
        if not np.all(np.isfinite(values)):
            raise UserError(f"{toml_path}: column {name} has non-finite values; nothing written")
    if n < 2:
        raise UserError(f"{toml_path}: the response has {n} sample(s); need at least 2")
    time = columns["t"]
    ts = float(f"{(time[-1] - time[0]) / (n - 1):.12g}")
    if controller is not None and abs(controller.sample_time - ts) > 1e-9 * ts:
        raise UserError(
            f"{toml_path}: controller sample_time {controller.sample_time} s differs "
            f"from the response's {ts} s"
        )
    overrides = check_plant_overrides(plant_overrides or {}, f"{toml_path} [plant]")

    lines = []
    if description:
        lines.append(f"description = {_toml_str(description)}")
    lines += [f'kind = "{kind}"', f"sample_time = {_toml_float(ts)}"]
    yd0 = float(np.asarray(response.velocity, dtype=float)[0])
    if yd0 != 0:
        lines.append(f"initial_velocity = {_toml_float(yd0)}   # [m/s]")
    units = ", ".join(f"{c} [{COLUMN_UNITS[c]}]" for c in names)
    lines.append(f"data = {_toml_str(csv_path.name)}   # columns {units}")
    if kind == "closed_loop":
        if controller is not None:
            lines += ["", "[controller]"] + _controller_lines(controller)
        lines += ["", "[reference]", 'kind = "column"']
    elif kind == "open_loop":
        lines += ["", "[input]", 'kind = "column"']
    else:
        lines += ["", "[tap]", "motor_connected = false"]
    if overrides:
        lines += ["", "[plant]"] + [f"{k} = {_toml_float(v)}" for k, v in overrides.items()]

    toml_path.parent.mkdir(parents=True, exist_ok=True)
    table = np.column_stack([columns[c] for c in names])
    with csv_path.open("w", newline="") as f:
        f.write(",".join(names) + "\n")
        np.savetxt(f, table, fmt="%.17g", delimiter=",")
    toml_path.write_text("\n".join(lines) + "\n")
    return toml_path


def experiment_paths(path: Path) -> tuple[Path, Path]:
    """(TOML, CSV) paths for a name given with either suffix, or none."""
    if path.suffix.lower() in (".toml", ".csv"):
        return path.with_suffix(".toml"), path.with_suffix(".csv")
    return path.with_name(path.name + ".toml"), path.with_name(path.name + ".csv")


def _controller_lines(pid: PID) -> list[str]:
    lines = [f"{k} = {_toml_float(float(getattr(pid, k)))}" for k in ("kp", "ki", "kd", "tau")]
    if pid.anti_windup == "back_calculation" or float(pid.kb) != 1.0:
        lines.append(f"kb = {_toml_float(float(pid.kb))}")
    if math.isfinite(float(pid.v_limit)):
        lines.append(f"v_limit = {_toml_float(float(pid.v_limit))}")
    lines += [f'derivative_on = "{pid.derivative_on}"', f'anti_windup = "{pid.anti_windup}"']
    return lines


def _toml_float(x: float) -> str:
    if math.isnan(x):
        raise ValueError("NaN cannot be written to an experiment file")
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(float(x))


def _toml_str(text: str) -> str:
    # A TOML basic string: escape backslash, quote and control characters.
    out = []
    for ch in str(text):
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append({"\n": "\\n", "\t": "\\t", "\r": "\\r"}.get(ch, f"\\u{ord(ch):04X}"))
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'
