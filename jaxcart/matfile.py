"""Recordings and simulation results as MATLAB .mat files, in the Simulink layouts that
:mod:`jaxcart.files` reads (docs/experiment-files.md, "MATLAB .mat layouts").

One run is written as ``name.mat`` (one variable per signal) and ``name.toml`` (the experiment
file, whose [data] table maps each signal to its variable), so that jaxcart reads it back and
MATLAB loads it as the lab's Simulink scopes save it. Layouts (``LAYOUTS``), for a signal y:

- ``"structure-with-time"`` (the default): ``y.time`` (N x 1 [s]), ``y.signals.values``
  (N x 1), ``y.signals.dimensions`` (1), ``y.signals.label``, ``y.blockName``;
- ``"structure"``: the same with ``y.time`` empty (the lab's 2.1pos.mat; samples then
  ``sample_time`` apart from t = 0);
- ``"array"``: ``y`` an N x 2 array [t, value];
- ``"vector"``: ``y`` an N x 1 column, with the time in a variable ``t``.

A run simulated from a recording whose data came from .mat files is written back as it came
in (:func:`source_layout`): the same layout, variable names and block names per signal.

>>> write_mat_experiment("run.mat", response, controller=pid)    # doctest: +SKIP
(PosixPath('run.toml'), PosixPath('run.mat'))
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hw import expfile as _expfile
from hw.atomicio import OutputError, atomic_open, atomic_paths, open_output
from jaxcart.errors import UserError
from jaxcart.plantspec import check_plant_overrides

# scipy.io (0.07-0.26 s) and h5py (0.07 s more) beside jax, python -X importtime on 2 cores, are
# imported where a .mat file is read or written: every experiment file read imports this module,
# and most are CSV. h5py reads v7.3 files only, and a clear error says when it is absent.

LAYOUTS = ("structure-with-time", "structure", "array", "vector")
DEFAULT_LAYOUT = "structure-with-time"
#: Signals written per kind (as in the CSV writer): t [s], y [m], v [V], r [m], e [m].
SIGNALS = {"closed_loop": ("y", "v", "r", "e"), "open_loop": ("y", "v"), "tap": ("y",)}
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}\Z")  # a MATLAB variable name


@dataclass(frozen=True)
class SignalLayout:
    """How one signal is stored: layout (one of ``LAYOUTS``), MATLAB variable name, and for
    the structures the scope's block name and signal label."""

    layout: str = DEFAULT_LAYOUT
    variable: str = "y"
    block_name: str = ""
    label: str = ""


def mat_paths(path) -> tuple[Path, Path]:
    """(TOML, MAT) paths for a name given as ``name.mat``, ``name.toml`` or ``name``."""
    path = Path(path)
    if path.suffix.lower() in (".toml", ".mat"):
        return path.with_suffix(".toml"), path.with_suffix(".mat")
    return path.with_name(path.name + ".toml"), path.with_name(path.name + ".mat")


# ---------------------------------------------------------------- the layout a file came in


def classify(obj) -> str | None:
    """The layout of one variable as ``scipy.io.loadmat(..., squeeze_me=True,
    struct_as_record=False)`` returns it, or None when it is none of ``LAYOUTS``."""
    # lazy: scipy.io costs 0.1 s at start-up (python -X importtime; the note at the top)
    from scipy.io.matlab import mat_struct

    if isinstance(obj, mat_struct):
        signals = getattr(obj, "signals", None)
        if not isinstance(signals, mat_struct | np.ndarray):  # one struct or a struct array
            return None
        time = np.asarray(getattr(obj, "time", np.zeros(0)))
        return "structure-with-time" if time.size else "structure"
    arr = np.asarray(obj)
    if arr.dtype.kind not in "biuf":
        return None
    arr = np.squeeze(arr)
    if arr.ndim == 2 and 2 in arr.shape:
        return "array"
    return "vector" if arr.ndim == 1 else None


def source_layout(recording) -> dict[str, SignalLayout]:
    """{signal: :class:`SignalLayout`} of each signal of ``recording`` (a
    :class:`jaxcart.files.Recording`) that was read from a .mat file; {} for CSV data.

    A recording from :func:`jaxcart.files.read_experiment` noted the layouts while it read its
    files (``Recording.mat_layout``): no file is read again. Any other recording's .mat files
    are loaded here, once each (a file that no longer loads counts as none)."""
    known = getattr(recording, "mat_layout", None)
    if known is not None:
        return dict(known)
    data = recording.meta.get("data")
    if not isinstance(data, dict):
        return {}
    folder = Path(recording.path).parent
    cache: dict = {}

    def load(file):
        if file not in cache:
            try:
                cache[file] = load_mat(folder / file)
            except (OSError, ValueError, NotImplementedError):
                cache[file] = {}
        return cache[file]

    return layouts(data, load)


def layouts(data, load) -> dict[str, SignalLayout]:
    """{signal: :class:`SignalLayout`} of the signals that an experiment file's [data] table
    ``data`` maps to .mat files, with ``load(file)`` the file's variables as
    ``scipy.io.loadmat(..., squeeze_me=True, struct_as_record=False)`` returns them (or None
    or {} when it does not load); {} when ``data`` is not a table."""
    if not isinstance(data, dict):
        return {}
    out = {}
    for name, source in data.items():
        file, _, variable = str(source).rpartition(":")
        if name == "t" or not file.lower().endswith(".mat"):
            continue
        variable = parse_variable(variable)[0]  # a muxed scope's signal is written alone
        obj = (load(file) or {}).get(variable)
        layout = classify(obj)
        if layout is None:
            continue
        block = label = ""
        if layout.startswith("structure"):
            block = _text(getattr(obj, "blockName", ""))
            first = np.ravel(obj.signals)[0]  # a struct array's first input
            label = _text(getattr(first, "label", ""))
        out[name] = SignalLayout(layout, variable, block, label)
    return out


def _text(value) -> str:
    return value if isinstance(value, str) else ""


def plan_layout(signals, layout=None, source=None) -> dict[str, SignalLayout]:
    """The :class:`SignalLayout` of each of ``signals``: ``layout`` for all when given, else
    each signal as ``source`` (from :func:`source_layout`) has it, the rest as the position's
    (or the default). Variable names are the source's when valid and distinct, else the
    signal's name."""
    source = dict(source or {})
    if layout is not None and layout not in LAYOUTS:
        raise UserError(f"layout {layout!r}: use one of {', '.join(LAYOUTS)}")
    fallback = layout or (source["y"].layout if "y" in source else DEFAULT_LAYOUT)
    plan, used = {}, set()
    for name in signals:
        src = source.get(name)
        variable = src.variable if src is not None and _NAME.match(src.variable) else name
        if variable in used or variable == "t":
            variable = name
        while variable in used or variable == "t":  # t is the vector layout's time
            variable += "_"
        used.add(variable)
        chosen = layout or (src.layout if src is not None else fallback)
        block = src.block_name if src is not None and src.block_name else f"jaxcart/{name}"
        label = src.label if src is not None else name
        plan[name] = SignalLayout(chosen, variable, block, label)
    return plan


# ---------------------------------------------------------------- writing


def _variable(values, time, spec: SignalLayout):
    column = np.asarray(values, dtype=float).reshape(-1, 1)
    if spec.layout == "array":
        return np.column_stack([time, column[:, 0]])
    if spec.layout == "vector":
        return column
    timed = spec.layout == "structure-with-time"
    return {
        "time": time.reshape(-1, 1) if timed else np.zeros((0, 0)),
        "signals": {"values": column, "dimensions": 1.0, "label": spec.label},
        "blockName": spec.block_name,
    }


def write_mat_experiment(
    path,
    response,
    *,
    controller=None,
    plant_overrides: dict | None = None,
    description: str | None = None,
    layout: str | None = None,
    source: dict | None = None,
    force: bool = False,
) -> tuple[Path, Path]:
    """Write one simulated run (a :class:`jaxcart.Response`) as ``name.mat`` + ``name.toml``;
    returns their paths (TOML, MAT).

    Signals: y [m] and, by kind, the command v [V], reference r [m] and error e [m], each a
    variable in ``layout`` (one of ``LAYOUTS``; None: as in ``source``, else
    "structure-with-time"). ``controller`` goes to [controller] (closed loop), ``plant_overrides``
    to [plant]. Values are float64 (an exact round trip). Refuses existing files unless
    ``force``, a batch of runs, a diverged run and non-finite values, as the CSV writer does.
    """
    arrays = {
        "y": response.position,
        "v": response.command,
        "r": response.reference,
        "e": response.error,
    }
    _, mat_path = mat_paths(path)
    if bool(np.any(np.asarray(response.diverged))):
        raise UserError(f"{mat_path}: the simulated run diverged; nothing written")
    yd0 = float(np.asarray(response.velocity, dtype=float).reshape(-1)[0])
    signals = {name: arrays[name] for name in SIGNALS[response.kind]}
    return _write(
        path,
        response.kind,
        response.time,
        signals,
        controller=controller if response.kind == "closed_loop" else None,
        overrides=plant_overrides,
        description=description,
        yd0=yd0,
        layout=layout,
        source=source,
        force=force,
    )


def write_mat_recording(path, recording, *, layout: str | None = None, force: bool = False):
    """Write a recording (a :class:`jaxcart.files.Recording`, e.g. from the hardware loop's
    CSV) as ``name.mat`` + ``name.toml``, in the layout its .mat data came in (default
    "structure-with-time"); returns (TOML, MAT). Its own signals only (y, and v and r where it
    has them, e = r - y with r), its controller, [plant], initial_velocity, description and
    provenance tables ([notes], [device], [timing], [run])."""
    signals = {"y": recording.position}
    if recording.command is not None:
        signals["v"] = recording.command
    if recording.reference is not None:
        signals["r"] = recording.reference
        signals["e"] = recording.reference - recording.position
    meta = recording.meta
    tables = {k: meta[k] for k in _expfile.FREE_TABLES if isinstance(meta.get(k), dict)}
    return _write(
        path,
        recording.kind,
        recording.time,
        signals,
        controller=recording.controller,
        overrides=recording.plant_overrides,
        description=meta.get("description"),
        yd0=float(recording.experiment.yd0),
        layout=layout,
        source=source_layout(recording),
        force=force,
        tables=tables,
        motor_connected=bool(meta.get("tap", {}).get("motor_connected", False)),
    )


def _write(
    path,
    kind,
    time,
    signals,
    *,
    controller,
    overrides,
    description,
    yd0,
    layout,
    source,
    force,
    tables=None,
    motor_connected=False,
):
    """Check everything, then write the .mat and the TOML (never over a file unless force)."""
    # lazy: scipy.io costs 0.1 s at start-up (python -X importtime; the note at the top)
    import scipy.io

    toml_path, mat_path = mat_paths(path)
    try:
        _expfile.check_free((toml_path, mat_path), force)
    except _expfile.ExpFileError as exc:
        raise UserError(str(exc)) from None
    names = tuple(signals)
    time = np.asarray(time, dtype=float)
    signals = {name: np.asarray(values, dtype=float) for name, values in signals.items()}
    if time.ndim != 1 or any(s.shape != time.shape for s in signals.values()):
        raise UserError(
            f"{mat_path}: the response holds a batch of runs (shape "
            f"{signals['y'].shape}); write one run at a time"
        )
    for name, values in {"t": time, **signals}.items():
        if not np.all(np.isfinite(values)):
            raise UserError(f"{mat_path}: signal {name} has non-finite values; nothing written")
    n = time.size
    if n < 2:
        raise UserError(f"{mat_path}: the response has {n} sample(s); need at least 2")
    ts = float(f"{(time[-1] - time[0]) / (n - 1):.12g}")
    if controller is not None and abs(controller.sample_time - ts) > 1e-9 * ts:
        raise UserError(
            f"{mat_path}: controller sample_time {controller.sample_time} s differs from the "
            f"response's {ts} s"
        )
    plan = plan_layout(names, layout, source)
    if time[0] != 0 and any(p.layout == "structure" for p in plan.values()):
        time = time - time[0]  # the Structure layout has no time: samples count from t = 0
    variables = {plan[k].variable: _variable(signals[k], time, plan[k]) for k in names}
    mapping = {k: f"{mat_path.name}:{plan[k].variable}" for k in names}
    if any(p.layout == "vector" for p in plan.values()):
        variables["t"] = time.reshape(-1, 1)
        mapping = {"t": f"{mat_path.name}:t", **mapping}
    overrides = check_plant_overrides(overrides or {}, f"{toml_path} [plant]")
    try:
        lines = _toml_lines(
            kind, ts, mapping, plan, controller, overrides, description, yd0, tables
        )
    except _expfile.ExpFileError as exc:
        raise UserError(f"{toml_path}: {exc}") from None
    if motor_connected:
        lines = ["motor_connected = true" if x == "motor_connected = false" else x for x in lines]
    _make_folder(mat_path)

    try:  # both under temporary names, renamed together: never one without the other
        with atomic_paths(mat_path, toml_path, force=force) as (mat_tmp, toml_tmp):
            with open_output(mat_tmp, "wb") as f:
                scipy.io.savemat(f, variables, oned_as="column", long_field_names=True)
            with open_output(toml_tmp, "w") as f:
                f.write("\n".join(lines) + "\n")
    except OutputError as exc:
        raise UserError(str(exc)) from None
    return toml_path, mat_path


def _make_folder(path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(
            f"{path}: cannot create the folder {path.parent} ({exc.strerror or exc}); choose "
            "another place"
        ) from None


def _toml_lines(kind, ts, mapping, plan, controller, overrides, description, yd0, tables):
    """The experiment file's lines: the CSV writer's, its data line replaced by [data]."""
    lines = _expfile.toml_lines(
        kind=kind,
        sample_time=ts,
        csv_name="-",
        columns=(),
        controller=controller if kind == "closed_loop" else None,
        plant=overrides,
        description=description,
        initial_velocity=yd0,
        tables=tables,
    )
    at = next(i for i, line in enumerate(lines) if line.startswith("data = "))
    units = _expfile.COLUMN_UNITS
    table = ["", "[data]   # MATLAB .mat variables (jaxcart.matfile)"]
    for name, where in mapping.items():
        note = f"{plan[name].layout}, " if name in plan else ""
        table.append(f"{name} = {_expfile.toml_str(where)}   # {note}[{units[name]}]")
    return lines[:at] + table + lines[at + 1 :]


# ---------------------------------------------------------------- results


def _field(name, used) -> str:
    """A valid, unique MATLAB field name for a key ("B_eq,f_c" -> "B_eq_f_c")."""
    text = re.sub(r"\W", "_", str(name)) or "x"
    if not text[0].isalpha():
        text = "x" + text
    text, base, k = text[:63], text[:60], 2
    while text in used:
        text, k = f"{base}_{k}", k + 1
    used.add(text)
    return text


def _matlab(value):
    """A JSON-like value as savemat writes it: dicts as structs, None as NaN, lists of numbers
    as row vectors, other lists as cell arrays."""
    if isinstance(value, dict):
        used: set = set()
        return {_field(k, used): _matlab(v) for k, v in value.items()}
    if value is None:
        return np.nan
    if isinstance(value, list | tuple):
        if value and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value):
            return np.asarray(value, dtype=float)[None, :]
        cell = np.empty((1, len(value)), dtype=object)
        for i, x in enumerate(value):
            cell[0, i] = _matlab(x)
        return cell
    return value


def write_mat_report(path, report: dict, *, name: str = "report", force: bool = False) -> Path:
    """Write a JSON-like result (e.g. ``fit --json``'s report) as one MATLAB struct ``name``
    in a .mat file: keys become field names (invalid characters to "_"), None becomes NaN,
    lists of numbers row vectors, other lists cell arrays. Refuses an existing file unless
    ``force``."""
    # lazy: scipy.io costs 0.1 s at start-up (python -X importtime; the note at the top)
    import scipy.io

    path = Path(path)
    if path.exists() and not force:
        raise UserError(f"{path} exists; choose another name or pass --force to overwrite it")
    _make_folder(path)

    try:  # a temporary name, renamed when complete: a full disk leaves no half file
        with atomic_open(path, "wb", force=force) as f:
            scipy.io.savemat(f, {name: _matlab(report)}, long_field_names=True)
    except OutputError as exc:
        raise UserError(str(exc)) from None
    return path


# ---------------------------------------------------------------- reading what scopes save


class LayoutError(ValueError):
    """A .mat variable in no layout the reader takes; the message says what to save instead."""


@dataclass(frozen=True, eq=False)
class ScopeSignal:
    """One signal of a .mat variable: values, its own time [s] or None, its label ("" when
    none), its place among the variable's signals (1-based, as MATLAB counts; an array's time
    column is not counted) and how many signals the variable holds."""

    values: np.ndarray
    time: np.ndarray | None
    label: str
    index: int
    count: int


_SELECTOR = re.compile(r"(?P<name>[^\[\]]+)\[(?P<sel>[^\[\]]+)\]\Z")


def parse_variable(variable: str) -> tuple[str, str | None]:
    """("var", selector or None) of a [data] variable written ``var``, ``var[2]`` (the 2nd
    signal of a muxed scope, counted from 1 as MATLAB does) or ``var[cart position]`` (the
    signal with that label)."""
    match = _SELECTOR.match(variable.strip())
    if match is None:
        return variable.strip(), None
    return match["name"].strip(), match["sel"].strip()


def load_mat(path) -> dict:
    """The variables of a .mat file as ``scipy.io.loadmat(path, squeeze_me=True,
    struct_as_record=False)`` returns them, MATLAB v7.3 (HDF5) files included: those are read
    with h5py into the same objects (structs as ``mat_struct``, arrays squeezed and in
    MATLAB's row-column order, text as str). Raises OSError/ValueError for a broken file."""
    # lazy: scipy.io costs 0.1 s at start-up (python -X importtime; the note at the top)
    import scipy.io

    try:
        return scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except NotImplementedError:  # scipy reads v4-v7; v7.3 is HDF5
        return _load_mat73(path)


def _load_mat73(path) -> dict:
    try:
        # lazy: h5py may be absent (v7.3 files only; the error below names it)
        import h5py
    except ImportError:  # pragma: no cover - a declared dependency
        raise ValueError("a MATLAB v7.3 file needs h5py (pip install h5py)") from None
    with h5py.File(path, "r") as f:
        return {name: _h5_value(f, f[name]) for name in f if not name.startswith("#")}


def _h5_class(obj) -> str:
    cls = obj.attrs.get("MATLAB_class", b"")
    return cls.decode() if isinstance(cls, bytes) else str(cls)


def _h5_value(f, obj):
    """One HDF5 object of a v7.3 file as scipy's squeezed reader gives it."""
    # lazy: h5py may be absent (v7.3 files only: reached through _load_mat73); scipy.io, 0.1 s
    import h5py
    from scipy.io.matlab import mat_struct

    if isinstance(obj, h5py.Group):
        names = list(obj.keys())
        order = obj.attrs.get("MATLAB_fields")
        if order is not None:  # MATLAB's field order (a vlen array of characters per field)
            names = [b"".join(np.asarray(x).astype("S1")).decode() for x in order]
        fields = {n: obj[n] for n in names if n in obj}
        refs = [d for d in fields.values() if _is_refs(d) and _h5_class(d) != "cell"]
        if refs and len(refs) == len(fields):  # a struct array: each field a list of references
            count = refs[0].size
            items = np.empty(count, dtype=object)
            for i in range(count):
                items[i] = _struct(
                    mat_struct, {n: _h5_value(f, f[d[()].ravel()[i]]) for n, d in fields.items()}
                )
            return items[0] if count == 1 else items
        return _struct(mat_struct, {n: _h5_value(f, d) for n, d in fields.items()})
    cls = _h5_class(obj)
    data = obj[()]
    if obj.attrs.get("MATLAB_empty", 0):
        return np.zeros(0)
    if cls == "char":
        return "".join(map(chr, np.asarray(data).T.ravel()))
    if _is_refs(obj):  # a cell array
        cells = np.empty(data.size, dtype=object)
        for i, ref in enumerate(np.asarray(data).T.ravel()):
            cells[i] = _h5_value(f, f[ref])
        return cells
    arr = np.asarray(data).T  # HDF5 holds MATLAB's column-major arrays transposed
    arr = np.squeeze(arr.astype(bool) if cls == "logical" else arr)
    return arr[()] if arr.ndim == 0 else arr


def _is_refs(obj) -> bool:
    # lazy: h5py may be absent (v7.3 files only: reached through _load_mat73)
    import h5py

    return isinstance(obj, h5py.Dataset) and obj.dtype == h5py.ref_dtype


def _struct(cls, fields: dict):
    out = cls()
    out._fieldnames = list(fields)
    for name, value in fields.items():
        setattr(out, name, value)
    return out


def scope_signals(obj, where: str) -> list[ScopeSignal]:
    """Every signal of one .mat variable (``where`` names it in errors): a Simulink scope
    structure (with or without time; ``signals`` one struct whose ``values`` has one column per
    signal, a muxed scope, or a struct array, a scope with several inputs), an array
    ``[t, value, ...]`` (N x 2, or N x k with time first: Simulink's "Array") or a vector.
    Raises :class:`LayoutError` for anything else."""
    # lazy: scipy.io costs 0.1 s at start-up (python -X importtime; the note at the top)
    from scipy.io.matlab import mat_struct

    if isinstance(obj, mat_struct):
        return _structure_signals(obj, where)
    values = _numeric(obj)
    if values is None:
        raise LayoutError(
            f"{where} is not numeric (a {type(obj).__name__}); give an N x 2 array "
            f"[t, value], a vector or a Simulink scope structure"
        )
    if values.ndim == 2 and values.shape[1] > values.shape[0]:
        values = values.T  # MATLAB's row form (2 x N)
    if values.ndim == 1 and values.size >= 2:
        return [ScopeSignal(values, None, "", 1, 1)]
    if values.ndim != 2 or values.shape[0] < 2:
        raise LayoutError(
            f"{where} has shape {values.shape}; give an N x 2 array [t, value], a vector or a "
            f"Simulink scope structure"
        )
    k = values.shape[1]
    time = values[:, 0].copy()
    if k > 2 and not np.all(np.diff(time) > 0):  # no time column: k signals
        return [ScopeSignal(values[:, i].copy(), None, "", i + 1, k) for i in range(k)]
    return [ScopeSignal(values[:, i].copy(), time, "", i, k - 1) for i in range(1, k)]


def _structure_signals(obj, where: str) -> list[ScopeSignal]:
    # lazy: scipy.io costs 0.1 s at start-up (python -X importtime; the note at the top)
    from scipy.io.matlab import mat_struct

    names = list(getattr(obj, "_fieldnames", []))
    if "signals" not in names:
        raise LayoutError(
            f"{where} is a structure without signals (fields: {', '.join(names)}); save the "
            f"scope as 'Structure With Time'"
        )
    signals = obj.signals
    parts = [signals] if isinstance(signals, mat_struct) else list(np.ravel(signals))
    if not parts or not all(isinstance(p, mat_struct) for p in parts):
        raise LayoutError(f"{where}.signals is not a structure; save the scope again")
    columns, labels = [], []
    for i, part in enumerate(parts):
        values = _numeric(getattr(part, "values", None))
        if values is None or values.ndim not in (1, 2):
            raise LayoutError(
                f"{where}.signals({i + 1}).values is not a column of numbers (shape "
                f"{np.shape(getattr(part, 'values', None))}); save the scope again"
            )
        block = values.reshape(values.shape[0], -1)
        columns += [block[:, j] for j in range(block.shape[1])]
        labels += _labels(getattr(part, "label", ""), block.shape[1])
    raw_time = _numeric(getattr(obj, "time", None))
    time = raw_time.ravel() if raw_time is not None and raw_time.size else None
    n = columns[0].size
    if any(c.size != n for c in columns):
        raise LayoutError(f"{where}: its signals differ in length; save the scope again")
    if time is not None and time.size != n:
        raise LayoutError(
            f"{where}.time has {time.size} samples, its values {n}; save the scope again"
        )
    k = len(columns)
    return [ScopeSignal(c, time, labels[i], i + 1, k) for i, c in enumerate(columns)]


def _labels(label, count: int) -> list[str]:
    """One label per column: a cell array of them, a string "a,b" split at commas (a muxed
    line's "<a>,<b>"), or one string for all."""
    if isinstance(label, np.ndarray) and label.dtype == object:
        texts = [_text(x) for x in label.ravel()]
    else:
        text = _text(label)
        texts = [p.strip() for p in text.split(",")] if count > 1 else [text]
    texts = [t.strip().strip("<>").strip() for t in texts]
    if len(texts) != count:
        texts = [texts[0] if texts else ""] * count
    return texts


def _numeric(obj):
    """obj as a squeezed 1-D or 2-D float64 array, or None if it is not numeric."""
    if obj is None:
        return None
    arr = np.asarray(obj)
    if arr.dtype.kind not in "biuf":
        return None
    arr = np.squeeze(arr.astype(float))
    return arr.reshape(1) if arr.ndim == 0 else arr


def select_signal(signals: list[ScopeSignal], selector: str | None, where: str) -> ScopeSignal:
    """The signal of a variable that ``selector`` names (``None``: the only one; "2": the
    second, counted from 1; other text: the signal with that label). Raises
    :class:`LayoutError` naming the choices."""
    k = len(signals)
    labels = [s.label for s in signals]
    listed = ", ".join(f"[{s.index}] {s.label!r}" if s.label else f"[{s.index}]" for s in signals)
    if selector is None:
        if k == 1:
            return signals[0]
        raise LayoutError(
            f"{where} holds {k} signals ({listed}); choose one as {where}[1] ... {where}[{k}] "
            f"(counted from 1, as MATLAB does) or by its label"
        )
    if selector.isdigit():
        i = int(selector)
        if 1 <= i <= k:
            return signals[i - 1]
        raise LayoutError(
            f"{where}[{selector}]: it holds {k} signal(s) ({listed}); choose 1 ... {k}"
        )
    want = selector.strip().strip("<>").strip().casefold()
    hits = [s for s in signals if s.label.casefold() == want]
    if len(hits) == 1:
        return hits[0]
    raise LayoutError(
        f"{where}[{selector}]: no single signal labelled so (labels: "
        f"{', '.join(repr(x) for x in labels) or 'none'}); choose by number, 1 ... {k}"
    )
