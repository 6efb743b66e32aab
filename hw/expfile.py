"""Experiment files, the project's exchange format, in numpy and the standard library only.

One TOML file per experiment, its data in a CSV file (docs/experiment-files.md):

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
    [device] [timing] [run]   free-form tables written by the hardware loop (hw/loop.py): the
                  device that ran, the sample-period statistics, and how the run ended

The CSV may also hold the loop's timing columns ``t_wall`` (when the sample was read, [s] from
the start) and ``compute`` (read to write, [s]); readers of the signals ignore them.

This module reads a file into plain numpy arrays and dicts (:func:`read_experiment_data`) and
writes one (:func:`write_experiment_file`); :mod:`jaxcart.files` builds the simulator's objects
on top (and reads MATLAB .mat data, which needs scipy, through the ``mat_reader`` hook). Every
problem is an :class:`ExpFileError` with one line naming the file, the field and what to do.

>>> import os, tempfile, numpy as np
>>> path = os.path.join(tempfile.mkdtemp(), "run.toml")
>>> t = np.arange(5) * 0.001
>>> _ = write_experiment_file(path, {"t": t, "y": 0.1 * t}, kind="tap")
>>> read_experiment_data(path).position.shape
(5,)
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hw.atomicio import OutputError, atomic_paths, open_output
from hw.control_law import (
    ANTI_WINDUP_MODES,
    DEFAULTS,
    DERIVATIVE_MODES,
    PID,
    PID_DATA_FIELDS,
    setting_problem,
)
from hw.csvio import CSVError, read_numeric_csv, write_numeric_csv
from hw.textfiles import HEAD, check_decodes, not_text, portable_path

KINDS = ("tap", "open_loop", "closed_loop")
#: Suffixes of data files (given where the experiment's TOML is expected, they are said so).
DATA_SUFFIXES = (".csv", ".txt", ".dat", ".mat", ".xlsx", ".xls", ".tsv")
#: Suffixes of text tables a [data] table maps columns of ("file.csv:column"; any case): named
#: columns separated by commas, semicolons, tabs or spaces.
TEXT_SUFFIXES = (".csv", ".tsv", ".txt")
COLUMNS = ("t", "y", "v", "r", "e")
COLUMN_UNITS = {"t": "s", "y": "m", "v": "V", "r": "m", "e": "m"}
#: Columns of the hardware loop's own timing, allowed in a CSV and ignored as signals.
TIMING_COLUMNS = ("t_wall", "compute")
TIMING_UNITS = {"t_wall": "s", "compute": "s"}
#: Free-form tables (any keys; values numbers, strings, booleans).
FREE_TABLES = ("notes", "device", "timing", "run")
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
) + FREE_TABLES
CONTROLLER_KEYS = PID_DATA_FIELDS + ("derivative_on", "anti_windup")
#: Keys of [reference] and [input] for each of their kinds (besides "kind").
SIGNAL_KEYS = {"step": ("amplitude",), "ramp": ("slope",), "column": ()}
TAP_KEYS = ("motor_connected",)
#: Allowed time-step deviation from sample_time (docs/experiment-files.md: more than 1 % off
#: is an error).
TIME_TOLERANCE = 0.01
#: Time stamps within this share of a sample of the uniform grid t_0 + k Ts are a uniform
#: clock read with jitter (a logger's own clock; the samples are taken as k Ts, and the
#: recording's check says how far they scatter), not a wrong sample_time or lost samples.
JITTER_SHARE = 0.25


class ExpFileError(ValueError):
    """An experiment file that cannot be read or written; the message is one line that names
    the file, the field or column, and what to fix."""


@dataclass(frozen=True, eq=False)
class ExperimentData:
    """One experiment file read into numpy arrays (float64) and plain dicts.

    path: the TOML file; meta: the parsed TOML; kind: "tap" | "open_loop" | "closed_loop"
    sample_time: Ts [s]; time: sample times [s] as recorded; position: y [m]
    command: v, the voltage the software sent [V], or None (no column v)
    reference: r [m] for closed loop (from [reference]), else None
    signal: what drives the experiment at t = k Ts: r [m] (closed loop), the input voltage [V]
        (open loop) or zeros (tap)
    y0: the first position [m]; yd0: initial_velocity [m/s]
    controller: the PID that ran (from [controller]), or None
    plant: the [plant] table as written (names are checked by jaxcart, which knows them)
    """

    path: Path
    meta: dict
    kind: str
    sample_time: float
    time: np.ndarray
    position: np.ndarray
    command: np.ndarray | None
    reference: np.ndarray | None
    signal: np.ndarray
    y0: float
    yd0: float
    controller: PID | None
    plant: dict

    @property
    def n_samples(self) -> int:
        return int(self.position.shape[0])


# ---------------------------------------------------------------- reading


#: How ``jaxcart simulate`` begins the description of what it writes: a simulation, which
#: the lab never takes for a recording of the cart (:func:`is_simulation`).
SIMULATED_BY = "jaxcart simulate"


def is_simulation(meta: dict) -> bool:
    """Whether an experiment file's tables (``meta``) are a run ``jaxcart simulate`` wrote."""
    return str(meta.get("description", "")).startswith(SIMULATED_BY)


def read_toml(path) -> dict:
    """The parsed TOML of an experiment file (one-line errors for a missing or broken file)."""
    path = Path(path)
    if path.is_dir():
        raise ExpFileError(f"experiment file {path} is a folder; give the path of a .toml file")
    if not path.is_file():
        raise ExpFileError(f"experiment file {path} not found; give the path of a .toml file")
    # An experiment is a TOML file that names its data; a data file given in its place is
    # said as such (docs/experiment-files.md).
    given_data = path.suffix.lower() in DATA_SUFFIXES
    also = (
        f" (an experiment is a .toml file that names its data, data = {toml_str(path.name)}; "
        f"see docs/experiment-files.md)"
        if given_data
        else ""
    )
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ExpFileError(f"{path}: cannot read it ({_one_line(exc)})") from None
    reason = not_text(raw[:HEAD], path) or check_decodes(raw, path)
    if reason:
        raise ExpFileError(reason + also)
    try:  # a UTF-8 byte-order mark (Notepad) is dropped, as in the CSV files
        return tomllib.loads(raw.decode("utf-8-sig"))
    except tomllib.TOMLDecodeError as exc:
        message = _one_line(exc)
        fix = "fix the syntax"
        if given_data:
            raise ExpFileError(f"{path} is a data file, not an experiment file{also}") from None
        if _backslash_at(raw.decode("utf-8-sig"), message):
            fix = (
                'a backslash in a "..." string starts an escape: write paths with forward '
                "slashes (data = \"runs/run.csv\") or in single quotes (data = 'runs\\run.csv')"
            )
        raise ExpFileError(f"{path}: not valid TOML ({message}); {fix}") from None


def read_experiment_data(path, *, mat_reader=None) -> ExperimentData:
    """Read an experiment file (TOML + CSV) into an :class:`ExperimentData`.

    Relative data paths are relative to the TOML file's folder. ``mat_reader(reader, file,
    variable, field) -> (values, time or None)`` reads signals mapped to MATLAB .mat files
    (jaxcart passes one built on scipy); without it such a file is refused with a message.
    Raises :class:`ExpFileError` with a one-line message for any problem.
    """
    path = Path(path)
    return Reader(path, read_toml(path), mat_reader).read()


class Signal:
    """One data column: values, its own time vector (or None) and how to name its rows."""

    def __init__(self, values, time, label, row):
        self.values, self.time, self.label, self.row = values, time, label, row


class Reader:
    """The checks of one experiment file; ``fail`` raises the one-line error."""

    def __init__(self, path: Path, meta: dict, mat_reader=None):
        self.path, self.meta, self.folder = path, _portable_data(meta), path.parent
        self.mat_reader = mat_reader
        self._csv_cache: dict = {}
        self.cache: dict = {}  # for the mat reader

    def fail(self, message: str):
        raise ExpFileError(f"{self.path}: {message}")

    # -- values

    def number(
        self, value, field, *, unit=None, positive=False, nonnegative=False, allow_inf=False
    ):
        """``value`` as a float; ``unit``: the field's unit, where a string holding a number
        and a unit (``"1 ms"``) is read too: in that unit, or one of :data:`_TO_SI` converted."""
        if isinstance(value, str) and unit is not None:
            value = self.quantity(value, field, unit)
        if isinstance(value, bool) or not isinstance(value, int | float):
            self.fail(f"{field} = {value!r}: give a number" + (f" (in {unit})" if unit else ""))
        value = float(value)
        if math.isnan(value) or (math.isinf(value) and not allow_inf):
            self.fail(f"{field} = {value!r}: give a finite number")
        if positive and not value > 0:
            self.fail(f"{field} = {value!r}: it must be positive")
        if nonnegative and not value >= 0:
            self.fail(f"{field} = {value!r}: it must be >= 0")
        return value

    def quantity(self, text, field, unit) -> float:
        """A number written with its unit (``"1 ms"``, ``"0.001 s"``, ``"40 mm"``) in ``unit``."""
        match = _QUANTITY.fullmatch(text)
        factor = None
        if match is not None:
            si, factor = _TO_SI.get(match["unit"], (unit if not match["unit"] else None, 1.0))
            factor = factor if si == unit else None
        if factor is None:
            self.fail(f"{field} = {text!r}: give a number in {unit} ({field} = 0.001, say)")
        return float(match["number"]) * factor

    def choice(self, value, field, allowed):
        value = _spelled(value, allowed)
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

    def read(self) -> ExperimentData:
        meta = self.meta
        for key in meta:
            if key not in TOP_KEYS:
                self.fail(f"unknown key {key!r}; allowed keys: {', '.join(TOP_KEYS)}")
        if "kind" not in meta:
            self.fail(f"no kind; add kind = one of {', '.join(map(repr, KINDS))}")
        # The kinds as the format spells them, wherever they are read from here on.
        for table, allowed in (
            (meta, KINDS),
            *((meta.get(t), SIGNAL_KEYS) for t in ("reference", "input")),
        ):
            if isinstance(table, dict) and "kind" in table:
                table["kind"] = _spelled(table["kind"], allowed)
        kind = self.choice(meta["kind"], "kind", KINDS)
        if "description" in meta and not isinstance(meta["description"], str):
            self.fail(f"description = {meta['description']!r}: give a string")
        for name in FREE_TABLES:
            if name in meta and not isinstance(meta[name], dict):
                self.fail(f"{name} must be a table [{name}]")
        yd0 = self.number(meta.get("initial_velocity", 0.0), "initial_velocity", unit="m/s")
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
        k = np.arange(n)
        position = self.position(kind, signals, k * ts)
        command = signals["v"].values if "v" in signals else None
        y0 = float(position[0])
        controller = reference = None
        if kind == "closed_loop":
            controller = self.controller(ts)
            spec = self.signal_spec("reference", "r", signals)
            reference = self.signal_from_spec(spec, signals, "r", k * ts, y0)
            self.check_reference_column(spec, reference, signals, time)
            signal = reference
        elif kind == "open_loop":
            spec = self.signal_spec("input", "v", signals)
            signal = self.signal_from_spec(spec, signals, "v", k * ts, 0.0)
        else:
            tap = self.table("tap", TAP_KEYS)
            if not isinstance(tap.get("motor_connected", False), bool):
                self.fail(f"[tap] motor_connected = {tap['motor_connected']!r}: give true or false")
            signal = np.zeros(n)
        plant = meta.get("plant", {})
        if not isinstance(plant, dict):
            self.fail(f"plant = {plant!r}: it must be a table [plant]")
        return ExperimentData(
            path=self.path,
            meta=meta,
            kind=kind,
            sample_time=ts,
            time=time,
            position=position,
            command=command,
            reference=reference,
            signal=np.asarray(signal, dtype=float),
            y0=y0,
            yd0=yd0,
            controller=controller,
            plant=dict(plant),
        )

    # -- data

    def position(self, kind, signals, t) -> np.ndarray:
        """y [m]: the column y, or a recorded error e = r - y through the reference (the
        handout's Error scope), y = r - e. With both y and e and no other reference, the
        reference is y + e (a column r)."""
        error = signals.get("e")
        if "y" in signals:
            if error is not None and kind == "closed_loop" and "r" not in signals:
                if "reference" not in self.meta:
                    r = signals["y"].values + error.values
                    signals["r"] = Signal(r, None, f"y + {error.label}", error.row)
            return signals["y"].values
        where = f"{error.label} (the error e = r - y [m]) without a position y"
        if kind != "closed_loop":
            self.fail(f"{where}: an error needs a reference; map y, or use kind = 'closed_loop'")
        spec = self.meta.get("reference")
        if isinstance(spec, dict) and spec.get("kind") == "step" and "amplitude" in spec:
            r = self.number(spec["amplitude"], "[reference] amplitude")
            return r - error.values
        if "r" in signals and not (isinstance(spec, dict) and spec.get("kind") != "column"):
            return signals["r"].values - error.values
        self.fail(
            f'{where}: give the reference, [reference] kind = "step" with amplitude = ... [m] '
            f"or a column r, so that y = r - e; or map y"
        )

    def signals(self) -> dict[str, Signal]:
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
            header, columns = self.unit_header(data, header, columns)
            unknown = [name for name in header if name not in COLUMNS + TIMING_COLUMNS]
            for required in ("t",) if "e" in columns else ("t", "y"):  # e: y = r - e
                if required not in columns:
                    guess = _guess(required, unknown)
                    self.fail(
                        f"column {required!r} missing in {data} (columns: "
                        f"{', '.join(header)}); name the {_LONG[required]} column "
                        f"{required} or map it in a [data] table ({required} = "
                        f'"{data}:{guess}")'
                    )
            if "" in unknown:  # pandas' to_csv writes its index as a first unnamed column
                self.fail(
                    f"{data} has a column without a name (a pandas index? write it with "
                    f"to_csv(..., index=False)); delete that column, or map the columns you "
                    f'need in a [data] table (e.g. t = "{data}:t", y = "{data}:y")'
                )
            if unknown:
                name = unknown[0]
                like = _looks_like(name)
                mapping = (
                    f'{like} = "{data}:{name}"'
                    if like
                    else f't = "{data}:t", y = "{data}:y"; a column such as {name!r} is then '
                    "left out"
                )
                self.fail(
                    f"column {name!r} of {data} is not one of {', '.join(COLUMNS)}; "
                    f"rename it, or map the columns you need in a [data] table (e.g. {mapping})"
                )
            return {
                name: Signal(values, None, f"{data} column {name}", _line_of(lines))
                for name, values in columns.items()
                if name in COLUMNS
            }
        if not isinstance(data, dict):
            self.fail(f"data = {data!r}: give a CSV file name or a [data] table")
        for key in data:
            if key not in COLUMNS:
                self.fail(
                    f"unknown key {key!r} in [data]; allowed: {', '.join(COLUMNS)} "
                    f"({', '.join(f'{c} [{u}]' for c, u in COLUMN_UNITS.items())})"
                )
        if "y" not in data and "e" not in data:
            self.fail(
                '[data] has no y; map the position [m]: y = "file.mat:variable" (or the '
                "error e = r - y [m] with the reference)"
            )
        return {name: self.mapped(name, source) for name, source in data.items()}

    def unit_header(self, data, header, columns):
        """(header, columns) with a column's unit dropped from its name where it is the
        format's own ("t [s]", "y (m)", "v [V]", "y_m": what a spreadsheet or writetable adds),
        and a column of the format in a unit it is often written in ("y [mm]", "t (ms)",
        "y_mm", "v [mV]") converted to the format's: the header says the unit, so the factor is
        not a guess. Any other unit is an error that says what to convert it to."""
        renamed, factors = {}, {}
        for name in header:
            found = named_unit(name)
            if found is None or found[0] not in COLUMN_UNITS:
                continue
            column, unit = found
            want = COLUMN_UNITS[column]
            si, factor = _TO_SI.get(unit, (None, None))
            if si != want:
                self.fail(
                    f"column {name!r} of {data} is in {unit!r}, a unit the reader does not "
                    f"convert; the format takes {_LONG[column]}: convert it to {want} and name "
                    f"the column {column}"
                )
            renamed[name], factors[name] = column, factor
        if not renamed:
            return header, columns
        header = [renamed.get(h, h) for h in header]
        if len(set(header)) != len(header):
            self.fail(f"{data}: repeated column names in the header {header}; name each once")
        return header, {renamed.get(h, h): v * factors.get(h, 1.0) for h, v in columns.items()}

    def mapped_unit(self, name, variable, field) -> float:
        """The factor to the format's unit of a column or variable mapped to ``name`` whose own
        name says its unit ("y [mm]", "t (ms)", "y_mm", "Position [cm]"): 1 where the name says
        no unit the reader knows. A unit of another quantity (a position in ms) is an error."""
        found = named_unit(variable)
        si, factor = _TO_SI.get(found[1], (None, 1.0)) if found else (None, 1.0)
        if si is not None and si != COLUMN_UNITS[name]:
            self.fail(
                f"{field} = {variable!r}: its name says {found[1]}, but {name} is the "
                f"{_LONG[name]}; map the column that holds it"
            )
        return factor

    def mapped(self, name, source) -> Signal:
        field = f"[data] {name}"
        if not isinstance(source, str) or ":" not in source:
            self.fail(f'{field} = {source!r}: give "file.mat:variable" or "file.csv:column"')
        file, variable = source.rsplit(":", 1)
        if file.lower().endswith(".mat"):
            if self.mat_reader is None:
                self.fail(
                    f"{field}: {file} is a MATLAB .mat file, which needs scipy; read it with "
                    f"jaxcart (jaxcart.files.read_experiment) or save the data as CSV"
                )
            values, time = self.mat_reader(self, file, variable, field)
            values = values * self.mapped_unit(name, variable, field)
            return Signal(values, time, source, lambda i: f"row {i + 1}")
        if file.lower().endswith(TEXT_SUFFIXES):
            header, columns, lines = self.read_csv(file, field)
            if variable not in columns:
                self.fail(
                    f"{field}: column {variable!r} missing in {file} (columns: "
                    f"{', '.join(header)}); map one of them"
                )
            values = columns[variable] * self.mapped_unit(name, variable, field)
            return Signal(values, None, source, _line_of(lines))
        if file.lower().endswith((".xlsx", ".xls")):
            self.fail(
                f"{field} = {source!r}: {file} is an Excel workbook; in Excel use File > Save As "
                f'> CSV UTF-8 and map its column ("{file.rsplit(".", 1)[0]}.csv:{variable}")'
            )
        self.fail(f"{field} = {source!r}: the file must be .mat or a text table (.csv, .tsv, .txt)")

    def data_path(self, name, field) -> Path:
        path = self.folder / name
        if path.is_dir():
            self.fail(
                f"{field}: data file {name} is a folder ({path}); give the path of the data "
                f"file inside it"
            )
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
        try:
            header, rows, lines = read_csv_rows(path, name)
        except ExpFileError as exc:
            self.fail(str(exc))
        except (OSError, UnicodeDecodeError) as exc:
            self.fail(f"{field}: cannot read {name} ({_one_line(exc)})")
        if header is None or len(rows) == 0:
            self.fail(f"{field}: {name} has no data rows; it needs a header line and samples")
        if len(set(header)) != len(header):
            self.fail(f"{name}: repeated column names in the header {header}; name each once")
        table = np.asarray(rows, dtype=float)
        result = header, {h: table[:, i] for i, h in enumerate(header)}, np.asarray(lines)
        self._csv_cache[name] = result
        return result

    def time(self, signals):
        """The time vector [s] and the sample time [s], after every consistency check."""
        sizes = {name: s.values.size for name, s in signals.items()}
        if len(set(sizes.values())) > 1:
            listing = ", ".join(f"{n} ({signals[n].label}) {sizes[n]}" for n in sizes)
            self.fail(f"data lengths differ: {listing} samples; give every signal the same samples")
        main = "y" if "y" in signals else "e"  # the position, or the error that stands for it
        n = sizes[main]
        if n < 2:
            self.fail(f"{signals[main].label}: {n} sample(s); a recording needs at least 2")
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
            ts = self.number(ts, "sample_time", unit="s", positive=True)
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
            self.time_fault(
                f"time of {source.label} does not increase at {source.row(i)} "
                f"(t = {float(time[i - 1])!r} then {float(time[i])!r} s)",
                "sort the samples or remove repeated rows",
                signals,
                source,
                ts,
            )
        declared = ts
        if ts is None:
            ts = float(f"{(time[-1] - time[0]) / (n - 1):.12g}")
            where = f"the mean step of {source.label}"
        else:
            where = f"sample_time = {ts!r} s"
        off = np.nonzero(np.abs(steps - ts) > TIME_TOLERANCE * ts)[0]
        if off.size and _jittered(time, ts):
            off = off[:0]  # stamps of a uniform clock, each read a little late or early
        if off.size:
            i = off[0] + 1
            step = float(steps[off[0]])
            ms = abs(step / (1000 * ts) - 1) <= TIME_TOLERANCE  # every step 1000 times Ts
            self.time_fault(
                f"time of {source.label} steps by {step:.6g} s at {source.row(i)}, more than "
                f"1 % from {where}",
                "the time looks recorded in ms: give t in s (divide it by 1000)"
                if ms and np.all(np.abs(steps / (1000 * ts) - 1) <= TIME_TOLERANCE)
                else "fix sample_time or resample the data to a uniform step",
                signals,
                source,
                declared,
            )
        return time, ts

    def time_fault(self, said, fix, signals, source, ts):
        """Fail on a time vector that is not one: ``said`` and ``fix``, or, where another
        column is an even time base, that the columns look swapped."""
        base = _time_base(signals, source, ts)
        if base is None:
            self.fail(f"{said}; {fix}")
        name, other = base
        time_name = next(n for n, s in signals.items() if s is source)
        self.fail(
            f"{said}, while {other.label} is an even time base "
            f"({_median_step(other.values):.6g} s steps from {float(other.values[0]):.6g} s): "
            f"the columns {time_name} and {name} look swapped; swap their names in the header, "
            "or map them in [data]"
        )

    # -- sections

    def controller(self, ts) -> PID | None:
        if "controller" not in self.meta:
            return None
        table = self.table("controller", CONTROLLER_KEYS)
        field = "[controller] {}".format
        values = {}
        for key in PID_DATA_FIELDS:  # the one rule of each number (hw.control_law)
            value = table.get(key, DEFAULTS[key])
            # A file records a run, which may have had a sign error (simulate writes what it
            # ran); the plausibility check flags such a loop as unstable before simulating.
            problem = setting_problem(key, value, allow_negative_gains=True)
            if problem:
                self.fail(f"{field(key)} = {problem}")
            values[key] = float(value)
        values["derivative_on"] = self.choice(
            table.get("derivative_on", "error"), field("derivative_on"), DERIVATIVE_MODES
        )
        values["anti_windup"] = self.choice(
            table.get("anti_windup", "none"), field("anti_windup"), ANTI_WINDUP_MODES
        )
        try:
            return PID(sample_time=ts, **values)
        except ValueError as exc:
            self.fail(f"[controller]: {_one_line(exc)}")

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

    def check_reference_column(self, spec, reference, signals, time):
        """A recorded column r beside a [reference] step must be that step: one that moves
        later says the step was recorded late (refused with the time it moves, where the data
        would otherwise be fitted against a step that never was)."""
        if spec["kind"] != "step" or "r" not in signals:
            return
        r = signals["r"].values
        tol = 1e-9 + 1e-6 * max(abs(float(reference[0])), float(np.max(np.abs(r))))
        off = np.nonzero(np.abs(r - reference) > tol)[0]
        if not off.size:
            return
        stays = np.nonzero(np.abs(r - reference) > tol)[0][-1] + 1
        when = (
            f"reaches it only at t = {float(time[stays]):.6g} s (the step was recorded late)"
            if stays < r.size
            else f"holds {float(r[off[0]]):.6g} m at t = {float(time[off[0]]):.6g} s"
        )
        self.fail(
            f"[reference] says a step to {float(reference[0]):g} m from t = 0, but "
            f"{signals['r'].label} {when}; to use the recorded reference, give [reference] "
            'kind = "column" (or no [reference])'
        )

    def signal_from_spec(self, spec, signals, column, t, offset):
        kind = spec["kind"]
        if kind == "column":
            return signals[column].values
        if kind == "step":
            return np.full(t.shape, float(spec["amplitude"]))
        return offset + float(spec["slope"]) * t


def read_csv_rows(path: Path, name: str):
    """(header, rows, line numbers) of a CSV file with a header line: rows a float64 array
    (rows x columns), read fast and in bounded memory by :mod:`hw.csvio` (progress on stderr
    for a large file).

    Blank lines and lines starting with # or % are skipped; a UTF-8 byte-order mark (Excel's "CSV
    UTF-8") is dropped. Raises :class:`ExpFileError` (message without the TOML file's name)
    for a line with the wrong number of fields or a value that is not a number.
    """
    try:
        return read_numeric_csv(path, name)
    except CSVError as exc:
        raise ExpFileError(str(exc)) from None


_LONG = {
    "t": "time [s]",
    "y": "position [m]",
    "v": "voltage [V]",
    "r": "reference [m]",
    "e": "error [m]",
}


def _jittered(time, ts) -> bool:
    """Whether ``time`` [s] keeps a mean step of ``ts`` (within TIME_TOLERANCE: else the
    sample time is wrong) and stays within JITTER_SHARE of a sample of its uniform grid
    (fitted through its median: a constant offset of every stamp is no jitter)."""
    if abs((time[-1] - time[0]) / (time.size - 1) - ts) > TIME_TOLERANCE * ts:
        return False
    return time_scatter(time, ts) <= JITTER_SHARE * ts


def time_scatter(time, ts) -> float:
    """How far [s] time stamps stray from the uniform grid of step ``ts`` through their median
    (a constant offset of every stamp is none): the largest distance."""
    scatter = np.asarray(time, dtype=float) - np.arange(len(time)) * ts
    return float(np.max(np.abs(scatter - np.median(scatter))))


def _spelled(value, allowed):
    """``value`` as one of ``allowed`` where it differs from it only in case, spaces and
    hyphens ("Closed loop", "closed-loop": "closed_loop"), else as it is."""
    if value in allowed or not isinstance(value, str):
        return value
    spelled = "_".join(value.strip().lower().replace("-", " ").split())
    return spelled if spelled in allowed else value


#: Words a column of each kind is often named with (what a hint to map it looks for).
_WORDS = {
    "t": ("time", "sec", "t"),
    "y": ("pos", "cart", "enc", "x", "y"),
    "v": ("volt", "command", "u", "v"),
    "r": ("ref", "set", "r"),
    "e": ("err", "e"),
}


def _looks_like(name: str) -> str | None:
    """The column of the format that ``name`` starts like (``Voltage`` a v, ``pos_cart`` a
    y), or None (a current, a speed: no column of the format)."""
    low = name.lower()
    words = [(w, c) for c, ws in _WORDS.items() for w in ws if len(w) > 1]
    return next((c for w, c in words if low.startswith(w)), None)


def _guess(column: str, names) -> str:
    """The name of ``names`` most likely to hold ``column`` (for a hint to map it): the first
    that starts with one of its words (``Time`` for t, ``position_mm`` for y), else the first
    name, else "column"."""
    for word in _WORDS[column]:
        for name in names:
            if name.lower().startswith(word):
                return name
    return names[0] if names else "column"


#: A column named with its unit: "t [s]", "y (m)", "v[V]", "Cart position [mm]", or with it as
#: a suffix: "y_mm", "t_ms" (the suffix one of the units a recording is often written in),
#: or after a word that names the suffix's quantity ("time_ms", "position_mm", "voltage_mV";
#: not "pos_s" or "v_sim_s", where the suffix is no unit).
_UNIT_HEADER = re.compile(
    r"(?P<name>\w[\w ]*?)\s*[\[(](?P<unit>[^\])]*)[\])]\Z"
    r"|(?P<stem>[A-Za-z])_(?P<suffix>s|ms|m|mm|cm|V|mV)\Z"
    r"|(?P<word>[A-Za-z]\w*?)_(?P<worded>s|ms|m|mm|cm|V|mV)\Z"
)
#: The words that name a quantity, by the unit the format takes it in.
_QUANTITY_WORDS = {
    "s": ("time", "tout"),
    "m": ("position", "pos", "cartposition", "cart_position", "error", "err", "reference", "ref"),
    "V": ("voltage", "volt", "volts", "command"),
}
#: A number and its unit, as a string (``"1 ms"``).
_QUANTITY = re.compile(
    r"\s*(?P<number>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>[\w/]*)\s*"
)
#: The units a recording is often written in: {unit: (the format's unit, factor to it)}.
_TO_SI = {
    "s": ("s", 1.0),
    "ms": ("s", 1e-3),
    "us": ("s", 1e-6),
    "m": ("m", 1.0),
    "mm": ("m", 1e-3),
    "cm": ("m", 1e-2),
    "V": ("V", 1.0),
    "v": ("V", 1.0),
    "mV": ("V", 1e-3),
}


def named_unit(name: str) -> tuple[str, str] | None:
    """(the name, its unit) of a column or variable named with its unit ("y [mm]", "t (ms)",
    "Position [cm]", "y_mm"), else None."""
    match = _UNIT_HEADER.match(name.strip())
    if match is None:
        return None
    if match["word"]:
        unit = match["worded"]
        si = _TO_SI[unit][0]
        return (match["word"], unit) if match["word"].lower() in _QUANTITY_WORDS[si] else None
    return match["name"] or match["stem"], (match["unit"] or match["suffix"]).strip()


def si_factor(name: str) -> float:
    """The factor that takes a column or variable named with a unit the reader knows ("t
    [ms]", "y_mm") to the format's unit (s, m, V); 1 for any other name."""
    found = named_unit(name)
    return _TO_SI.get(found[1], (None, 1.0))[1] if found else 1.0


def _backslash_at(text: str, message: str) -> bool:
    """Whether the line a TOML error names holds a backslash in a "..." string: a Windows
    path ("C:\\Users" is an invalid \\U escape, "runs\\data" an unknown \\d)."""
    found = re.search(r"at line (\d+)", message)
    lines = text.splitlines()
    if not found or not 0 < int(found.group(1)) <= len(lines):
        return False
    line = lines[int(found.group(1)) - 1]
    return '"' in line and "\\" in line


def _portable_data(meta: dict) -> dict:
    """``meta`` with its data paths as the user meant them: a Windows path in a TOML basic
    string ("runs\\run.csv" holds a carriage return) mended, backslashes read as folder
    separators (:func:`hw.textfiles.portable_path`); anything else in the file is kept."""
    data = meta.get("data")
    if isinstance(data, str):
        return {**meta, "data": portable_path(data)}
    if isinstance(data, dict):
        mended = {k: portable_path(v) if isinstance(v, str) else v for k, v in data.items()}
        return {**meta, "data": mended}
    return meta


def _line_of(lines):
    return lambda i: f"line {int(lines[i])}"


def _time_base(signals, source, ts) -> tuple[str, Signal] | None:
    """(name, signal) of another signal than ``source`` that is an even time base (strictly
    increasing by one step, ``ts`` where given, within TIME_TOLERANCE), or None: the clue to
    swapped columns."""
    for name, signal in signals.items():
        values = signal.values
        if signal is source or values.size < 3:
            continue
        steps = np.diff(values)
        step = _median_step(values)
        if step <= 0 or (ts is not None and abs(step - ts) > TIME_TOLERANCE * ts):
            continue
        if np.all(np.abs(steps - step) <= TIME_TOLERANCE * step):
            return name, signal
    return None


def _median_step(time):
    return float(np.median(np.diff(time))) if time.size > 1 else 0.0


def _one_line(exc) -> str:
    return " ".join(str(exc).split())


# ---------------------------------------------------------------- writing


def experiment_paths(path) -> tuple[Path, Path]:
    """(TOML, CSV) paths for a name given with either suffix, or none."""
    path = Path(path)
    if path.suffix.lower() in (".toml", ".csv"):
        return path.with_suffix(".toml"), path.with_suffix(".csv")
    return path.with_name(path.name + ".toml"), path.with_name(path.name + ".csv")


def check_free(paths, force: bool = False) -> None:
    """Refuse (:class:`ExpFileError`) if any of ``paths`` exists, unless ``force``."""
    for path in paths:
        if Path(path).exists() and not force:
            raise ExpFileError(
                f"{path} exists; choose another name or pass --force (force=True) to overwrite it"
            )


def toml_lines(
    *,
    kind: str,
    sample_time: float,
    csv_name: str,
    columns,
    controller: PID | None = None,
    plant: dict | None = None,
    description: str | None = None,
    initial_velocity: float = 0.0,
    tables: dict | None = None,
) -> list[str]:
    """The lines of an experiment file's TOML (the reference or input is the CSV column)."""
    if kind not in KINDS:
        raise ExpFileError(f"kind = {kind!r}: use one of {', '.join(KINDS)}")
    lines = []
    if description:
        lines.append(f"description = {toml_str(description)}")
    lines += [f'kind = "{kind}"', f"sample_time = {toml_float(sample_time)}"]
    if initial_velocity != 0:
        lines.append(f"initial_velocity = {toml_float(initial_velocity)}   # [m/s]")
    units = {**COLUMN_UNITS, **TIMING_UNITS}
    listing = ", ".join(f"{c} [{units.get(c, '-')}]" for c in columns)
    lines.append(f"data = {toml_str(csv_name)}   # columns {listing}")
    if kind == "closed_loop":
        if controller is not None:
            lines += ["", "[controller]"] + controller_lines(controller)
        lines += ["", "[reference]", 'kind = "column"']
    elif kind == "open_loop":
        lines += ["", "[input]", 'kind = "column"']
    else:
        lines += ["", "[tap]", "motor_connected = false"]
    if plant:
        lines += ["", "[plant]"] + [f"{k} = {toml_float(v)}" for k, v in plant.items()]
    for name, table in (tables or {}).items():
        if name not in FREE_TABLES:
            raise ExpFileError(f"table [{name}]: the free-form tables are {', '.join(FREE_TABLES)}")
        lines += ["", f"[{name}]"] + [f"{_key(k)} = {toml_value(v)}" for k, v in table.items()]
    return lines


def write_experiment_file(
    toml_path,
    columns: dict,
    *,
    kind: str,
    sample_time: float | None = None,
    controller: PID | None = None,
    plant: dict | None = None,
    description: str | None = None,
    initial_velocity: float = 0.0,
    tables: dict | None = None,
    force: bool = False,
) -> Path:
    """Write ``columns`` ({name: 1-D array}, ``t`` and ``y`` first) as ``name.toml`` + ``name.csv``.

    Values are written in their shortest exact form (``repr``: exact round trip), in blocks
    (:func:`hw.csvio.write_numeric_csv`: bounded memory); ``sample_time`` defaults
    to the mean step of ``t``. ``controller`` goes to [controller], ``plant`` ({name: number})
    to [plant], ``tables`` ({"notes" | "device" | "timing" | "run": {key: value}}) to free-form
    tables. Refuses to overwrite either file unless ``force``. Returns the TOML path.
    """
    toml_path, csv_path = experiment_paths(toml_path)
    check_free((toml_path, csv_path), force)
    names = tuple(columns)
    arrays = [np.asarray(columns[c], dtype=float) for c in names]
    n = arrays[0].shape[0]
    if any(a.shape != (n,) for a in arrays):
        raise ExpFileError(f"{toml_path}: every column must be 1-D of the same length")
    if sample_time is None:
        t = np.asarray(columns["t"], dtype=float)
        sample_time = float(f"{(t[-1] - t[0]) / (n - 1):.12g}")
    lines = toml_lines(
        kind=kind,
        sample_time=sample_time,
        csv_name=csv_path.name,
        columns=names,
        controller=controller,
        plant=plant,
        description=description,
        initial_velocity=initial_velocity,
        tables=tables,
    )
    # Both files under temporary names, renamed together (the CSV first: a TOML never points
    # at a missing CSV): a full disk or a crash leaves neither, so the rerun is not blocked.
    try:
        with atomic_paths(csv_path, toml_path, force=force) as (csv_tmp, toml_tmp):
            with open_output(csv_tmp, "w", newline="") as f:
                write_numeric_csv(f, names, arrays, name=csv_path.name)
            with open_output(toml_tmp, "w") as f:
                f.write("\n".join(lines) + "\n")
    except OutputError as exc:
        raise ExpFileError(str(exc)) from None
    return toml_path


def controller_lines(pid: PID) -> list[str]:
    lines = [f"{k} = {toml_float(float(getattr(pid, k)))}" for k in ("kp", "ki", "kd", "tau")]
    if pid.anti_windup == "back_calculation" or float(pid.kb) != 1.0:
        lines.append(f"kb = {toml_float(float(pid.kb))}")
    if math.isfinite(float(pid.v_limit)):
        lines.append(f"v_limit = {toml_float(float(pid.v_limit))}")
    lines += [f'derivative_on = "{pid.derivative_on}"', f'anti_windup = "{pid.anti_windup}"']
    return lines


def toml_float(x: float) -> str:
    x = float(x)
    if math.isnan(x):
        raise ValueError("NaN cannot be written to an experiment file")
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(x)


def toml_value(value) -> str:
    """A TOML value from a bool, number or string (numpy scalars too)."""
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        x = float(value)
        return '"nan"' if math.isnan(x) else toml_float(x)
    if isinstance(value, str | os.PathLike):
        return toml_str(str(value))
    raise ExpFileError(f"cannot write {value!r} to a TOML table; give a number or a string")


def _key(name) -> str:
    name = str(name)
    if name and all(ch.isalnum() or ch in "_-" for ch in name):
        return name
    return toml_str(name)


def toml_str(text: str) -> str:
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
