"""Experiment files, the project's exchange format: one TOML file per experiment, data in CSV or
MATLAB .mat (docs/experiment-files.md).

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

The format itself (TOML + CSV into numpy arrays, and back) is :mod:`hw.expfile`, numpy only, so
that the hardware loop writes what this module reads; here are what needs JAX or scipy: MATLAB
.mat data (scipy.io), the :class:`Recording` with its :class:`jaxcart.Experiment`, and the plant
built from [plant]. Every problem is a :class:`UserError` with one line naming the file, the field
and what to do.

>>> rec = read_experiment("p50.toml")                              # doctest: +SKIP
>>> rec.kind, rec.position.shape, rec.controller.kp                # doctest: +SKIP
('closed_loop', (2705,), 50.0)
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from hw import expfile as _expfile
from hw.control_law import PID
from hw.expfile import (  # noqa: F401  (the format's names, re-exported for jaxcart's users)
    COLUMN_UNITS,
    COLUMNS,
    CONTROLLER_KEYS,
    SIGNAL_KEYS,
    TAP_KEYS,
    TIME_TOLERANCE,
    TOP_KEYS,
    ExpFileError,
    experiment_paths,
)
from jaxcart import matfile, plausibility
from jaxcart.errors import UserError
from jaxcart.experiments import Experiment
from jaxcart.matimport import is_csv, run_of, split_source
from jaxcart.params import Plant
from jaxcart.plantspec import build_plant, check_plant_overrides
from jaxcart.smooth_sim import Response


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
    warnings: what looks physically doubtful (:mod:`jaxcart.plausibility`), one line each
    signal: the experiment's signal as read (r_k [m] or u_k [V]), float64 numpy: the
        Experiment's copy follows the JAX mode it was made in (float32 without x64, 0.4 m
        kept as 0.40000001 m), so fits, which run in float64, start from this one
    mat_layout: {signal: :class:`jaxcart.matfile.SignalLayout`} of the signals read from
        .mat files, noted while they were read ({} for CSV data; None for a recording that
        :func:`read_experiment` did not read), so :func:`jaxcart.matfile.source_layout`
        need not load the files again
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
    warnings: tuple[str, ...] = ()
    signal: np.ndarray | None = None
    mat_layout: dict | None = None

    def signal64(self) -> np.ndarray:
        """The experiment's signal in float64 [m or V] (see ``signal``)."""
        if self.signal is not None:
            return self.signal
        return np.asarray(self.experiment.signal, dtype=np.float64)

    @property
    def n_samples(self) -> int:
        return int(self.position.shape[0])

    def as_response(self):
        """The recording as a :class:`jaxcart.Response` (numpy arrays), for step_info and plots:
        velocity by central differences [m/s]; reference r (or y0 when there is none); command
        and voltage both the recorded v (zeros without a column v)."""
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
        return build_plant(self.plant_overrides, base=base, where=f"{self.path} [plant]")

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
        signal = self.signal64()
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


def signal64(recording) -> np.ndarray:
    """A recording's experiment signal in float64 [m or V]: :meth:`Recording.signal64` where
    it has one, else its experiment's signal."""
    if isinstance(recording, Recording):
        return recording.signal64()
    return np.asarray(recording.experiment.signal, dtype=np.float64)


# ---------------------------------------------------------------- reading


#: The built-in example recordings (synthetic; tuning/lab/data.py made them), shipped with
#: the package. ``jaxcart examples`` copies them into a folder of the user's.
BUILTIN_DATA = Path(__file__).resolve().parent / "data"
#: Where ``jaxcart examples`` copies them when given no folder.
EXAMPLES_DIR = "jaxcart-examples"


def builtin_recording(name) -> Path | None:
    """The built-in file of the same name as ``name`` (``tap.toml``, ``p50.csv``), or None."""
    path = BUILTIN_DATA / Path(name).name
    return path if Path(name).name and path.is_file() else None


def _not_found_hint(path) -> None:
    """A missing experiment file named like a built-in recording: where that one is, and how
    to copy them all (raised as the one-line error)."""
    path = Path(path)
    builtin = builtin_recording(path.name)
    if path.exists() or builtin is None or path.suffix.lower() != ".toml":
        return
    raise UserError(
        f"experiment file {path} not found; the built-in recording {path.name} is {builtin}: "
        f"jaxcart examples copies the built-in recordings into ./{EXAMPLES_DIR}/ (then cd "
        f"{EXAMPLES_DIR}), or give the path of your own .toml file"
    )


def read_experiment(path, *, check: bool = True, experiment: str | None = None) -> Recording:
    """Read an experiment file (TOML + CSV/.mat data); see the module docstring for the format.

    A raw .mat file as QUARC/Simulink saved it (no TOML) is read too: its experiment is
    recognised from its content and names (:mod:`jaxcart.matimport`; ``experiment``, one of
    :data:`jaxcart.recognition.EXPERIMENTS`, names it instead), the guess and its evidence are
    printed to stderr, and weak evidence is a UserError that asks the user to name it.
    Relative data paths are relative to the TOML file's folder. Raises :class:`UserError` with a
    one-line message for any problem in the file or its data. With ``check`` (the default) the
    recording is checked for physical sense (:mod:`jaxcart.plausibility`): positions far off
    the track raise a UserError, milder doubts are printed once to stderr and kept in
    ``Recording.warnings``.
    """
    raw = split_source(path)  # "file.mat" or "file.mat:scope[1]": a raw scope file, no TOML
    if raw is not None:
        toml = raw[0].with_suffix(".toml")
        if is_csv(raw[0]) and toml.is_file():  # the data of an experiment file: read that
            raise UserError(f"{raw[0]} is the data of {toml}: give {toml.name}")
        # Named with the variable chosen: two runs of one file are two names in a fit.
        name = raw[0] if raw[1] is None else raw[0].with_name(f"{raw[0].name}:{raw[1]}")
        return read_imported(run_of(path, experiment), name, check=check)
    _not_found_hint(path)
    return _recording(
        lambda mat_reader: _expfile.read_experiment_data(path, mat_reader=mat_reader), check
    )


def read_imported(run, path=None, *, check: bool = True, quiet: bool = False) -> Recording:
    """The :class:`Recording` of a run of raw .mat files (a :class:`jaxcart.matimport.Imported`)
    through the experiment file its recognised (or named) experiment implies, held in memory;
    ``path`` (default: :attr:`~jaxcart.matimport.Imported.name`) names it. The guess and its
    evidence go to stderr unless ``quiet``. A run that is no recording, or whose evidence is
    weak, is a UserError (one line; the weak one asks the user to name the experiment)."""
    path = Path(path) if path is not None else run.name
    if run.problem:
        raise UserError(run.problem)
    if not run.usable():
        how = f"with jaxcart import {path.name} --as PART (or read_experiment(..., experiment=))"
        raise UserError(run.guess.question(path.name, how))
    meta = run.meta()
    if not quiet:
        print("jaxcart: " + "\njaxcart: ".join(run.lines()), file=sys.stderr)
    return _recording(lambda mat_reader: _expfile.Reader(path, meta, mat_reader).read(), check)


def _recording(load, check: bool) -> Recording:
    """The :class:`Recording` of ``load(mat_reader)`` (an :class:`hw.expfile.ExperimentData`),
    checked for physical sense when ``check``."""
    mats: dict = {}  # {file: its loaded variables}, each file loaded once (reader.cache)

    def mat_reader(reader, name, variable, field):
        out = _read_mat(reader, name, variable, field)
        mats[name] = reader.cache[name]
        return out

    try:
        data = load(mat_reader)
    except ExpFileError as exc:
        raise UserError(str(exc)) from None
    mat_layout = {}
    if mats:  # the layout each signal came in, from the variables already loaded
        mat_layout = matfile.layouts(data.meta.get("data"), mats.get)  # the files are not kept
    overrides = check_plant_overrides(data.plant, f"{data.path} [plant]")
    experiment = Experiment(
        jnp.asarray(data.signal),
        y0=data.y0,
        yd0=data.yd0,
        kind=data.kind,
        sample_time=data.sample_time,
    )
    rec = Recording(
        path=data.path,
        kind=data.kind,
        sample_time=data.sample_time,
        time=data.time,
        position=data.position,
        command=data.command,
        reference=data.reference,
        controller=data.controller,
        plant_overrides=overrides,
        experiment=experiment,
        meta=data.meta,
        signal=np.asarray(data.signal, dtype=np.float64),
        mat_layout=mat_layout,
    )
    if not check:
        return rec
    rec, found = _late_step(rec)
    warnings = found + tuple(plausibility.check_recording(rec))
    for message in warnings:
        plausibility.warn(message)
    return dataclasses.replace(rec, warnings=warnings)


def _late_step(rec) -> tuple[Recording, tuple[str, ...]]:
    """The recording with its step where the data put it (:func:`plausibility.late_step`), and
    the warning that says so; as it was, and no warning, when the step is at t = 0."""
    k0 = plausibility.late_step(rec)
    if k0 is None:
        return rec, ()
    r = np.where(np.arange(rec.n_samples) < k0, rec.position[0], rec.reference[-1])
    t0 = k0 * rec.sample_time
    said = (
        f"{rec.path}: the step starts at t = {t0:.3f} s, not at t = 0 as [reference] says: the "
        f"recorded command v stays at rest until then and follows [controller] stepped there "
        f"({rec.command[k0]:.3g} V at t = {t0:.3f} s); the reference is taken to step at "
        f"{t0:.3f} s (cut the rows before it, or give the reference as a column r, to say so "
        "in the file)"
    )
    experiment = dataclasses.replace(rec.experiment, signal=jnp.asarray(r))
    return dataclasses.replace(rec, reference=r, signal=r, experiment=experiment), (said,)


def _read_mat(reader, name, variable, field):
    """Values and time (or None) of ``name:variable``, a .mat file's variable (MATLAB v4-v7
    with scipy.io, v7.3 with h5py); ``variable[2]`` or ``variable[label]`` picks one signal of
    a muxed scope (:func:`jaxcart.matfile.parse_variable`)."""
    path = reader.data_path(name, field)
    cache = reader.cache
    if name not in cache:
        try:
            cache[name] = matfile.load_mat(path)
        except Exception as exc:  # scipy and h5py raise several kinds for a broken file
            reader.fail(f"{field}: cannot read {name} as a .mat file ({_one_line(exc)})")
    mat = cache[name]
    base, selector = matfile.parse_variable(variable)
    names = [k for k in mat if not k.startswith("__")]
    if base not in names:
        reader.fail(
            f"{field}: variable {base!r} not in {name} (variables: "
            f"{', '.join(names) or 'none'}); map one of them"
        )
    try:
        signals = matfile.scope_signals(mat[base], f"{name}:{base}")
        chosen = matfile.select_signal(signals, selector, f"{name}:{base}")
    except matfile.LayoutError as exc:
        reader.fail(f"{field}: {exc}")
    return chosen.values, chosen.time


def _one_line(exc) -> str:
    return " ".join(str(exc).split())


# ---------------------------------------------------------------- plants


def default_base(kind: str, meta: dict | None = None) -> Plant:
    """The nominal plant of an experiment kind: the handout's, or the unplugged motor of a tap."""
    unplugged = kind == "tap" and not (meta or {}).get("tap", {}).get("motor_connected", False)
    return build_plant(motor_connected=not unplugged, where=f"a {kind} experiment's plant")


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
    every value in its shortest exact form (exact round trip). The reference (or open-loop
    input) is recorded as a column. ``controller`` and ``plant_overrides`` go to [controller]
    and [plant]. Refuses to overwrite either file unless ``force``. Returns the TOML path.
    """
    toml_path, csv_path = experiment_paths(Path(toml_path))
    try:
        _expfile.check_free((toml_path, csv_path), force)
    except ExpFileError as exc:
        raise UserError(str(exc)) from None
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
    yd0 = float(np.asarray(response.velocity, dtype=float)[0])
    try:
        return _expfile.write_experiment_file(
            toml_path,
            columns,
            kind=kind,
            sample_time=ts,
            controller=controller,
            plant=overrides,
            description=description,
            initial_velocity=yd0,
            force=force,
        )
    except ExpFileError as exc:
        raise UserError(str(exc)) from None
