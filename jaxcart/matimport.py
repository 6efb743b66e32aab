"""Raw QUARC/Simulink .mat files to experiment files, without a hand-written TOML.

The lab's scopes save each signal in the layout the scope was set to (docs/experiment-files.md,
"MATLAB .mat layouts"): an N x 2 array [t, value] (``part1.1.mat``), a "Structure" with an
empty time (``2.1pos.mat``, ``2.1volt.mat``: one signal per file), a "Structure With Time"
(``p50_repeat.mat``: position and voltage in one file), a muxed scope (several columns, or a
struct array, in one variable), MATLAB v7.3 (HDF5) files. This module

1. reads every variable of the files and names each signal's role from its variable name,
   label and block name (position y, voltage v, error e = r - y, reference r, time t), else
   from its content (positions are whole encoder counts; voltages exceed the track's metres);
   a signal saved twice (the same values, any layout or time) is one signal, and the
   pendulum's sensor is none of the cart's;
2. puts the signals of one run together: the variables of one file, and files whose names
   differ only by the signal ("2.1pos.mat" + "2.1volt.mat") and that hold as many samples;
3. recognises the experiment of each run (:mod:`jaxcart.recognition`) and writes the experiment
   file it implies (:meth:`Imported.toml_text`): kind, sample time, the [data] table that maps
   each signal to its variable, the controller and reference or input the evidence gives, the
   evidence itself as comments and in [notes].

>>> runs = scan(["2.1pos.mat", "2.1volt.mat", "part1.1.mat"])     # doctest: +SKIP
>>> [(r.label, r.guess.experiment) for r in runs]                 # doctest: +SKIP
[('2.1pos.mat + 2.1volt.mat', 'p_step'), ('part1.1.mat', 'tap')]

A CSV file of named columns without an experiment file (another simulator's, a spreadsheet's:
"time,position,voltage") is a raw recording too: each column a signal whose role its name (else
its content) gives, the time column the run's time, mapped as "file.csv:column".

Units: s, m, V. A sample time is the data's own; a file without time (the "Structure" layout)
is taken at the lab's 1 kHz (``ASSUMED_SAMPLE_TIME``) and says so.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hw.atomicio import write_text
from hw.csvio import CSVError, read_numeric_csv
from hw.expfile import TEXT_SUFFIXES, si_factor, toml_value
from jaxcart import matfile
from jaxcart.errors import UserError
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.recognition import EXPERIMENTS, MOVING_SPEED, Guess, Traces, recognise

#: The lab's QUARC sample time [s], for data saved without time.
ASSUMED_SAMPLE_TIME = 0.001
ROLES = ("y", "v", "e", "r")
_ROLE_WORDS = (  # first match wins: "voltage out" is a voltage, "cart position" a position
    # "t", "time", "tout" and their numbered or suffixed forms ("t1", "time1", "t_tap",
    # "tout1", "time [s]"): MATLAB users number the runs of one session
    ("t", r"^(t|time|tout|tt)([\d_ \[(].*)?$"),
    ("?", r"rod|pendulum|angle|alpha|theta"),  # the pendulum's sensor, not the cart's loop
    # What the model does not read: a speed, an acceleration, a current, a force.
    (
        "-",
        r"veloc|speed|accel|current|force|dot(?![a-z])|(?<![a-z])(amps?|xd|yd|dx|dy|i|f)(?![a-z])",
    ),
    ("e", r"err|(?<![a-z])e(?![a-z])"),
    ("v", r"volt|(?<![a-z])(v|u|vm|um)(?![a-z])|motor|command|control|drive|input"),
    ("r", r"ref|setpoint|set point|desired|slider|(?<![a-z])r(?![a-z])"),
    ("y", r"pos|cart|(?<![a-z])(y|x)(?![a-z])|encoder|output|displacement|distance"),
)


@dataclass(frozen=True, eq=False)
class RawSignal:
    """One signal found in a .mat file: the file, its [data] source ("file.mat:var" or
    "file.mat:var[k]"), values, its own time [s] or None, role (y, v, e, r, t or "?") and how
    the role was found, and the names it came with."""

    file: Path
    source: str
    values: np.ndarray
    time: np.ndarray | None
    role: str
    why: str
    names: tuple[str, ...]
    #: The Simulink model that saved it (its blockName's first part: "labcartsat"), or None.
    model: str | None = None


@dataclass(eq=False)
class Imported:
    """One run put together from raw .mat files: its files, signals by role, sample time
    [s] (and whether it was assumed), the guess, what kept it from being a recording
    (``problem``, one line) if anything, the ``copies`` (kept, copy) of a signal saved twice
    and the signals ``ignored`` (neither the cart's position, voltage, error nor reference)."""

    files: list[Path]
    signals: dict = field(default_factory=dict)
    sample_time: float = ASSUMED_SAMPLE_TIME
    time_assumed: bool = True
    guess: Guess | None = None
    problem: str | None = None
    copies: list = field(default_factory=list)
    ignored: list = field(default_factory=list)
    #: Which of a file's runs, where one file holds several (:func:`runs_in`): the Simulink
    #: model that saved it ("labcartsat"); None for the only one.
    part: str | None = None

    @property
    def label(self) -> str:
        files = " + ".join(p.name for p in self.files)
        return files if self.part is None else f"{files} ({self.part})"

    @property
    def stem(self) -> str:
        """A name for its experiment file: the first file's stem (and its part)."""
        part = "" if self.part is None else "-" + re.sub(r"[^\w.-]+", "_", self.part)
        return self.files[0].stem + part

    @property
    def name(self) -> Path:
        """What its recording is named by (a fit's tables and nuisances, the lab's lines): the
        first file, or where the file holds several runs, the position (else error) chosen,
        ``FILE.mat:VARIABLE``, as :func:`jaxcart.files.read_experiment` names a run chosen so."""
        return self.files[0] if self.part is None else self.files[0].with_name(self.anchor.source)

    @property
    def anchor(self) -> RawSignal:
        """Its position, else its error (what FILE.mat:VARIABLE chooses it by)."""
        return self.signals["y"] if "y" in self.signals else self.signals["e"]

    @property
    def experiment(self) -> str | None:
        return None if self.guess is None else self.guess.experiment

    def usable(self) -> bool:
        """True when it is a recording of a named or confidently recognised experiment."""
        return self.problem is None and self.guess is not None and self.guess.confident

    def lines(self) -> list[str]:
        """What was found and why, one line each."""
        head = [f"{self.label}:"]
        roles = ", ".join(f"{k} = {s.source} ({s.why})" for k, s in self.signals.items())
        if roles:
            head.append(f"  signals: {roles}")
        for kept, copy in self.copies:
            timing = "its own time" if copy.time is not None else "no time"
            head.append(
                f"  {copy.source} is a copy of {kept.source} (the same {copy.values.size} "
                f"values to the encoder count, {timing}): one signal"
            )
        for s in self.ignored:
            head.append(f"  not used: {s.source} ({s.why})")
        when = "assumed (no time in the data)" if self.time_assumed else "from the data"
        head.append(f"  sample time {self.sample_time:g} s, {when}")
        if self.guess is not None:
            head += ["  " + line for line in self.guess.lines()]
        if self.problem:
            head.append(f"  {self.problem}")
        return head

    def meta(self, toml_folder=None) -> dict:
        """The experiment file's tables ({key: value}, as tomllib would read them), its data
        mapped as "file.mat:var" relative to ``toml_folder`` (None: the data's own folder).
        Raises :class:`UserError` when the run is not a recording of one experiment."""
        if self.problem:
            raise UserError(self.problem)
        if self.guess is None or self.guess.experiment is None:
            raise UserError(f"{self.label}: no experiment recognised; name it")
        return _meta(self, toml_folder)

    def toml_text(self, toml_folder=None) -> str:
        """The experiment file (in ``toml_folder``): the meta as TOML, the evidence as
        comments."""
        return _toml_text(self, self.meta(toml_folder))


# ---------------------------------------------------------------- reading the files


#: The suffixes of raw recordings (any case): the scopes' .mat files; text tables of named
#: columns without an experiment file.
RAW_SUFFIXES = (".mat", *TEXT_SUFFIXES)


def is_csv(path) -> bool:
    """A text table (:data:`hw.expfile.TEXT_SUFFIXES`), not a MATLAB file."""
    return Path(path).suffix.lower() in TEXT_SUFFIXES


def read_signals(path: Path) -> list[RawSignal]:
    """Every signal of every variable of one .mat file (every column of a CSV file), each with
    its role. Raises :class:`UserError` (one line) for a file that does not load."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file; give the path of a .mat or .csv file")
    if is_csv(path):
        return _csv_signals(path)
    try:
        variables = matfile.load_mat(path)
    except Exception as exc:  # scipy and h5py raise several kinds for a broken file
        raise UserError(f"{path}: cannot read it as a .mat file ({_one_line(exc)})") from None
    out = []
    for name, obj in variables.items():
        if name.startswith("__"):
            continue
        try:
            signals = matfile.scope_signals(obj, f"{path.name}:{name}")
        except matfile.LayoutError:
            continue  # not a signal (a parameter, a text): not the scope's
        block = _text(getattr(obj, "blockName", ""))
        factor = si_factor(name)  # a variable named with its unit ("y_mm"): in m
        for s in signals:
            s = dataclasses.replace(s, values=np.asarray(s.values) * factor) if factor != 1 else s
            selector = f"[{s.index}]" if s.count > 1 else ""
            names = tuple(x for x in (name, s.label, block) if x)
            role, why = _role(names, s, many=s.count > 1)
            out.append(
                RawSignal(
                    path,
                    f"{path.name}:{name}{selector}",
                    s.values,
                    s.time,
                    role,
                    why,
                    names,
                    block.split("/", 1)[0].strip() or None if "/" in block else None,
                )  # fmt: skip
            )
    return out


def _csv_signals(path: Path) -> list[RawSignal]:
    """The columns of a CSV file as signals, each named by its header (the time column by its
    name: the run's time)."""
    try:
        header, table, _ = read_numeric_csv(path, path.name)
    except CSVError as exc:
        raise UserError(str(exc)) from None
    if header is None or table.shape[0] < 2:
        raise UserError(f"{path}: no header line and rows of numbers; not a recording")
    out = []
    for k, name in enumerate(header):
        column = _Column(table[:, k] * si_factor(name))  # "t [ms]", "y_mm": in s, m, V
        role, why = _role((name,), column, many=False)
        if _is_row_index(name, table[:, k]):  # pandas' to_csv: an unnamed index first
            role, why = "?", "a row index (0, 1, 2, ...), not a signal"
        out.append(RawSignal(path, f"{path.name}:{name}", column.values, None, role, why, (name,)))
    index = _is_row_index(header[0], table[:, 0])  # counts rows, not seconds: 1 kHz assumed
    if all(s.role != "t" for s in out) and _is_clock(out[0].values) and not index:
        # No column named time: the first, where it ticks at a steady step, as in every CSV.
        out[0] = dataclasses.replace(out[0], role="t", why="the first column, a steady clock")
    return out


#: Header names of a row index (pandas writes its index unnamed, or "Unnamed: 0" once read
#: back and written again).
_INDEX_NAMES = ("", "index", "idx", "row", "#", "n", "k", "sample", "samples")


def _is_row_index(name: str, values) -> bool:
    """Whether a column is a row index: named as one (:data:`_INDEX_NAMES`, "Unnamed: ...")
    and counting 0, 1, 2, ... (or from 1)."""
    low = name.strip().lower()
    if low not in _INDEX_NAMES and not low.startswith("unnamed"):
        return False
    return bool(values[0] in (0.0, 1.0) and np.all(np.diff(values) == 1.0))


def _is_clock(values) -> bool:
    """Whether ``values`` rise at a steady step (within 5 %) from near 0, as a time column."""
    step = np.diff(values)
    if step.size < 2 or not np.all(step > 0):
        return False
    return bool(abs(values[0]) <= 10 * step[0] and np.ptp(step) <= 0.05 * np.mean(step))


@dataclass(frozen=True)
class _Column:
    """A CSV column as :func:`_role` reads a signal (no time of its own)."""

    values: np.ndarray
    time: None = None


def _role(names, signal, *, many: bool) -> tuple[str, str]:
    """(role, why) of one signal: from its names (variable, label, block; the last segment of
    a block path first), else from its values."""
    texts = []
    for text in names:
        # A block path's first segment is the model ("labcartpid/rod"): it names the lab,
        # not the signal.
        texts += [text.rsplit("/", 1)[-1], text.split("/", 1)[-1]]
    for text in texts:
        low = text.lower()
        for role, pattern in _ROLE_WORDS:
            if role == "t" and (many or signal.time is not None):
                continue
            if re.search(pattern, low):
                if role == "-":
                    return "?", f"name {text!r}: a signal the model does not read"
                whose = ": the pendulum's, not the cart's" if role == "?" else ""
                return role, f"name {text!r}{whose}"
    values = signal.values  # time only by name: a voltage ramp increases too
    if float(np.max(np.abs(values))) > 1.0:
        return "v", "values beyond 1 (V, not m on the 1 m track)"
    step = _count_of(values)
    if step is not None and 0.5 * ENCODER_RESOLUTION <= step <= 2 * ENCODER_RESOLUTION:
        return "y", f"whole encoder counts of {step:.5g} m"
    changes = int(np.count_nonzero(np.diff(values)))
    if step is not None and changes > 10:  # a sensor that dithers, not a reference's levels
        return "?", (
            f"whole counts of {step:.4g} that change {changes} times: another sensor's "
            f"encoder (the pendulum's?), not the cart's {ENCODER_RESOLUTION:.4g} m"
        )
    if np.unique(values).size <= 10:
        return "r", "a few constant levels (a reference)"
    if not many:  # a scope's own signal, smooth: what the software computed
        return "v", "not whole encoder counts (a voltage)"
    return "?", "no name or content that says what it is"


def _count_of(values) -> float | None:
    """The count of an encoder (its unit) when every change of ``values`` is a whole number
    of one step and the values also stand still or change by several counts at a time (a
    voltage ramp changes by the same step every sample), else None."""
    steps = np.abs(np.diff(values))
    moved = steps[steps > 0]
    if moved.size == 0:
        return None
    count = float(moved.min())
    ratio = moved / count
    if not np.all(np.abs(ratio - np.rint(ratio)) < 1e-3):
        return None
    return count if moved.size < steps.size or np.ptp(np.rint(ratio)) > 0 else None


def _text(value) -> str:
    return value if isinstance(value, str) else ""


def _one_line(exc) -> str:
    return " ".join(str(exc).split())


# ---------------------------------------------------------------- runs


_STEM_WORDS = re.compile(
    r"pos(ition)?|volt(age)?|err(or)?|ref(erence)?|cart|command|input|output|signal"
)


def siblings(path: Path) -> list[Path]:
    """The .mat files beside ``path`` whose names differ from its only by the signal
    (2.1pos.mat: 2.1volt.mat), any case of the suffix."""
    key = run_key(path)
    if is_csv(path):  # a CSV file holds its run's columns together
        return []
    return [p for p in files_of(Path(path).parent) if key and p != path and run_key(p) == key]


def files_of(folder: Path, suffixes=(".mat",)) -> list[Path]:
    """The files of ``folder`` with one of ``suffixes`` (default the .mat files), sorted, any
    case of the suffix (a Windows copy or rename may give "PART1.1.MAT")."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in suffixes and p.is_file())


def run_key(path: Path) -> str:
    """A file's name without the signal words: "2.1pos.mat" and "2.1volt.mat" give "2.1"."""
    stem = _STEM_WORDS.sub("", Path(path).stem.lower())
    return re.sub(r"[\s_\-]+", "", stem).strip(".")


def scan(
    paths, *, named: dict | None = None, chosen: dict | None = None, one_run: bool = False
) -> list[Imported]:
    """The runs in the .mat files ``paths``, each recognised (``named``: {file name:
    experiment} the user named, taken as the answer; ``chosen``: {file name: variable} the
    position the user chose, e.g. "scope[1]"). Files that hold only a voltage or a reference
    join the run of a file with a position (or error) whose name differs only by the signal
    (whatever their names where ``one_run``: the user named the files as one run) and that
    holds as many samples."""
    named = dict(named or {})
    per_file = {Path(p): read_signals(p) for p in paths}
    several = {}  # a file that holds several runs: [(part, signals), ...]
    for path, signals in per_file.items():
        found = runs_in(signals)
        if len(found) > 1:
            several[path] = found
    for path, variable in (chosen or {}).items():
        path = next(p for p in per_file if p.name == Path(path).name)
        picked = _choose(path, per_file[path], variable)
        if path in several:  # the chosen signal's run alone
            several[path] = [_chosen_part(several[path], per_file[path], picked)]
        else:
            per_file[path] = picked
    anchors, partners, runs = [], [], []
    for path, signals in per_file.items():
        if path in several:
            continue
        if any(s.role in ("y", "e") for s in signals):
            anchors.append(path)
        elif signals:
            partners.append(path)
        else:
            runs.append(Imported([path], problem=f"{path.name}: no signal saved by a scope in it"))
    groups = {path: [path] for path in anchors}
    for path in partners:
        n = per_file[path][0].values.size
        fits = [
            a
            for a in anchors
            if (one_run or run_key(a) == run_key(path)) and per_file[a][0].values.size == n
        ]
        if len(fits) == 1:
            groups[fits[0]].append(path)
        else:
            what = ", ".join(sorted({s.role for s in per_file[path]}))
            runs.append(
                Imported(
                    [path],
                    problem=f"{path.name} holds no position (signals: {what}) and "
                    f"{'no' if not fits else 'more than one'} file with a position has its "
                    f"name and length; map it in an experiment file's [data] table",
                )
            )
    found = [(files, [s for f in files for s in per_file[f]], None) for files in groups.values()]
    found += [([path], signals, part) for path, each in several.items() for part, signals in each]
    for files, signals, part in found:
        run = _assemble(files, signals)
        run.part = part
        if (
            run.problem is None
            and part is not None
            and files[0].name in named
            and not (chosen or {}).get(files[0].name)
        ):
            run.problem = (  # which of the file's runs the name is for, only the user knows
                f"{files[0].name} holds {len(several[files[0]])} runs ("
                f"{', '.join(m for m, _ in several[files[0]])}); name the one you mean by its "
                f"position or error, e.g. {run.anchor.source}"
            )
        if run.problem is None:
            choice = next((named[f.name] for f in files if f.name in named), None)
            run.guess = recognise(_traces(run), choice)
        runs.append(run)
    return runs


def runs_in(signals: list[RawSignal]) -> list[tuple[str | None, list[RawSignal]]]:
    """The runs one file's ``signals`` hold: [(part, signals)], one run (part None) unless
    they come from two or more Simulink models (the first part of each blockName:
    "labcartsat/cart", "labcartcolint/error") of different lengths, each with a position or
    an error of its own (a workspace saved after two experiments: the real cart's lab1_4.1.mat,
    a P step's 3135 samples from labcartsat and a PI step's 6200 from labcartcolint). A signal
    without a model (an N x 2 array) joins the model of its length; anything else keeps the
    file one run, as saved (two runs of one model or one length are the user's to map). A
    part is named by its model."""
    by_model: dict[str, list[RawSignal]] = {}
    loose = []
    for s in signals:
        (by_model.setdefault(s.model, []) if s.model else loose).append(s)
    lengths = {m: {s.values.size for s in g} for m, g in by_model.items()}
    if len(by_model) < 2 or any(len(n) != 1 for n in lengths.values()):
        return [(None, signals)]
    size = {m: next(iter(n)) for m, n in lengths.items()}
    if len(set(size.values())) != len(size):
        return [(None, signals)]
    for s in loose:
        home = [m for m, n in size.items() if n == s.values.size]
        if len(home) != 1:
            return [(None, signals)]  # a signal of no model's length: one run, as saved
        by_model[home[0]].append(s)
    if not all(any(s.role in ("y", "e") for s in g) for g in by_model.values()):
        return [(None, signals)]
    return sorted(by_model.items(), key=lambda item: (size[item[0]], item[0]))


def _chosen_part(parts, signals, picked) -> tuple[str, list[RawSignal]]:
    """The part of ``parts`` that holds the signal the user chose (``picked``: the file's
    ``signals`` with the choice made), with the choice made in it; an error chosen stays the
    error (its run's position, if recorded, stays the position)."""
    (mine,) = [k for k, s in enumerate(picked) if s.why == CHOSEN]
    was = signals[mine]
    for part, members in parts:
        if any(m is was for m in members):
            if was.role == "e":
                return part, members
            keep = {id(m) for m in members}
            return part, [c for c, o in zip(picked, signals, strict=True) if id(o) in keep]
    raise AssertionError("every signal is in a part")  # pragma: no cover


def _assemble(files, signals) -> Imported:
    run = Imported(list(files))
    by_role: dict[str, list[RawSignal]] = {}
    for s in signals:
        by_role.setdefault(s.role, []).append(s)
    for role in ("y", "e", "v", "r", "t"):
        found = _copies_as_one(run, by_role.get(role, []), role)
        by_role[role] = found
        if len(found) > 1:
            listed = ", ".join(s.source for s in found)
            if role in ("y", "e"):  # FILE.mat:variable chooses the position (or error)
                fix = (
                    f"choose the one to use: jaxcart import {found[0].source} (or map it in an "
                    f"experiment file's [data] table)"
                )
            else:  # FILE.mat:variable would take it for the position: map the run instead
                mapped = [f'{k} = "{s.source}"' for k, s in run.signals.items()]
                mapped.append(f'{role} = "{found[0].source}"')
                fix = (
                    "two runs in one file? write an experiment file whose [data] table maps "
                    f"one run's signals, e.g. [data] {', '.join(mapped)}"
                )
            run.problem = (
                f"{run.label}: {len(found)} different signals look like {_LONG[role]} "
                f"({listed}); {fix}"
            )
            return run
        if found and role != "t":
            run.signals[role] = found[0]
    unknown = by_role.get("?", [])
    run.ignored = list(unknown)
    if unknown and "y" not in run.signals and "e" not in run.signals:
        run.problem = f"{run.label}: no signal that is a position; map it in [data]"
        return run
    for s in run.signals.values():
        bad = np.flatnonzero(~np.isfinite(s.values))
        if bad.size:  # the experiment reader refuses it too; say so before recognising
            run.problem = (
                f"{s.source} holds {s.values[bad[0]]} at sample {bad[0] + 1} ({bad.size} "
                f"such); every sample must be a finite number: save the scope again or cut "
                f"the bad samples"
            )
            return run
    n = {s.values.size for s in run.signals.values()}
    if len(n) > 1:
        run.problem = (
            f"{run.label}: its signals hold different numbers of samples ("
            + ", ".join(f"{s.source} {s.values.size}" for s in run.signals.values())
            + "); save them from one run"
        )
        return run
    timed = [s.time for s in run.signals.values() if s.time is not None]
    if by_role["t"]:
        timed.insert(0, by_role["t"][0].values)
        run.signals["t"] = by_role["t"][0]
    if timed and timed[0].size > 1:
        time = timed[0]
        run.sample_time = float(f"{(time[-1] - time[0]) / (time.size - 1):.12g}")
        run.time_assumed = False
    return run


def _copies_as_one(run: Imported, found: list[RawSignal], role: str) -> list[RawSignal]:
    """The different signals among ``found`` (all of one role): a copy (as many samples, the
    same values to within half an encoder count, or 1 uV for a voltage, whatever its time or
    layout) is the same signal saved twice, kept once (the first that carries its own time)
    and listed in ``run.copies``."""
    kept: list[RawSignal] = []
    for s in sorted(found, key=lambda s: s.time is None):  # stable: the timed ones first
        twin = next((k for k in kept if _same_values(k, s, role)), None)
        if twin is None:
            kept.append(s)
        else:
            run.copies.append((twin, s))
    return kept


def _same_values(a: RawSignal, b: RawSignal, role: str) -> bool:
    if a.values.shape != b.values.shape:
        return False
    tol = 1e-6 if role == "v" else 0.5 * ENCODER_RESOLUTION if role != "t" else 0.0
    return bool(np.all(np.abs(a.values - b.values) <= tol))


_LONG = {"y": "a position", "v": "a voltage", "e": "an error", "r": "a reference", "t": "time"}


def _traces(run: Imported) -> Traces:
    values = {k: s.values for k, s in run.signals.items() if k in ROLES}
    names = [f.stem for f in run.files]
    for s in run.signals.values():
        names += list(s.names)
    return Traces(
        sample_time=run.sample_time,
        position=values.get("y"),
        command=values.get("v"),
        error=values.get("e"),
        reference=values.get("r"),
        names=tuple(dict.fromkeys(names)),
    )


# ---------------------------------------------------------------- the experiment file


def _meta(run: Imported, toml_folder) -> dict:
    guess = run.guess
    spec = EXPERIMENTS[guess.experiment]
    data = {}
    for k, s in run.signals.items():
        prefix = "" if toml_folder is None else data_prefix(toml_folder, s.file.parent)
        data[k] = prefix + s.source
    meta = {
        "description": f"{spec.what} (Part ({spec.part})), imported from {run.label}",
        "kind": spec.kind,
        "sample_time": run.sample_time,
        "data": data,
    }
    where = f"{run.label} ({guess.experiment})"
    if spec.kind == "tap":
        meta["tap"] = {"motor_connected": False}
    elif spec.kind == "open_loop":
        if "v" in data:
            meta["input"] = {"kind": "column"}
        else:
            meta["input"] = {"kind": "ramp", "slope": guess.ramp}
    else:
        if guess.controller is not None:
            meta["controller"] = dict(guess.controller)
        if "r" not in data and not ("e" in data and "y" in data):
            if guess.experiment == "slider":
                raise UserError(
                    f"{where}: slider moves, but the reference (the slider's setpoint) is not "
                    "recorded; save it with the scope and map it as r (or the error as e)"
                )
            step = guess.step
            if step is None and "e" in data:
                step = float(run.signals["e"].values[0])  # e(0) = r - y(0), the cart at 0
            if step is None:
                raise UserError(
                    f"{where}: the step's size is unknown (no voltage, reference or error "
                    f'recorded); write the experiment file with [reference] kind = "step", '
                    f"amplitude = ... [m]"
                )
            meta["reference"] = {"kind": "step", "amplitude": step}
        else:  # the reference recorded, or r = y + e
            step = _final_reference(run)
        if spec.step is not None and not math.isclose(step, spec.step, rel_tol=0.01):
            meta["description"] += f"; its step {step:.4g} m, not the handout's"
    meta["notes"] = {
        "imported_from": run.label,
        "recognised_as": guess.experiment,
        "evidence": "; ".join(e.text for e in guess.evidence) or "none",
        "strength": "named by the user" if guess.named else "strong" if guess.confident else "weak",
        "sample_time_assumed": run.time_assumed,
    }
    late = late_start(run)
    if late:  # every command that reads the file warns (plausibility.check_integral_start)
        meta["notes"]["late_start"] = late[0]
    return meta


def _final_reference(run: Imported) -> float:
    """The reference [m] at the last sample (a step's, wherever it steps): recorded, or the
    position plus the error."""
    if "r" in run.signals:
        return float(run.signals["r"].values[-1])
    return float(run.signals["y"].values[-1] + run.signals["e"].values[-1])


def late_start(run: Imported) -> list[str]:
    """A warning where an error scope under integral action starts far below the handout's
    step: the step is then read as the first error (the cart at rest at 0), but a scope that
    kept only a run's last samples starts there too, with the integral built up (the real
    cart's 4.1e.mat: the same samples as 4.1err.mat, whose time starts at t = 15 s)."""
    guess = run.guess
    if guess is None or guess.experiment is None or run.problem or "e" not in run.signals:
        return []
    spec = EXPERIMENTS[guess.experiment]
    gains = guess.controller or spec.controller or {}
    if "y" in run.signals or "r" in run.signals or not gains.get("ki") or spec.step is None:
        return []
    e = np.asarray(run.signals["e"].values, dtype=float)
    e0 = float(e[0])
    if abs(e0) >= spec.step / 4:
        return []
    # A step that moves the cart from rest sets it off at once; a scope that starts mid-run
    # finds it at rest or creeping (4.1e.mat: 5 mm in 7.7 s). (A step too small to move the
    # cart until its integral has grown looks like a tail: the warning says "if".)
    k = max(int(round(0.01 / run.sample_time)), 1)
    early = e[: max(int(round(0.2 / run.sample_time)), k + 1)]
    speed = np.max(np.abs(early[k:] - early[:-k])) / (k * run.sample_time) if early.size > k else 0
    if speed > MOVING_SPEED:
        return []
    return [
        f"the error starts at {e0 * 1e3:.3g} mm, not at a step like the handout's "
        f"{spec.step:g} m: read as a step of {e0 * 1e3:.3g} mm from rest; if the scope "
        f"started after the step (it kept only the run's last samples), the integral (ki = "
        f"{gains['ki']:g} V/(m s)) had built up by then, which the simulations start at 0: "
        "fits of this run would be wrong; record the run from its step"
    ]


def _toml_text(run: Imported, meta: dict) -> str:
    lines = [f"# Written by jaxcart import from {run.label}: correct any line and rerun."]
    lines += [f"# {line}" for line in run.lines()[1:]]
    for key, value in meta.items():
        if not isinstance(value, dict):
            lines.append(f"{key} = {toml_value(value)}")
    for key, value in meta.items():
        if isinstance(value, dict):
            lines += ["", f"[{key}]"] + [f"{k} = {toml_value(v)}" for k, v in value.items()]
    return "\n".join(lines) + "\n"


def data_prefix(toml_folder, data_folder) -> str:
    """How an experiment file in ``toml_folder`` names data in ``data_folder``: a relative
    path ("" for the same folder, "../data/"), or the absolute one across drives."""
    toml_folder, data_folder = Path(toml_folder).resolve(), Path(data_folder).resolve()
    try:
        rel = os.path.relpath(data_folder, toml_folder)
    except ValueError:  # another drive (Windows)
        return data_folder.as_posix() + "/"
    return "" if rel == "." else Path(rel).as_posix() + "/"


def write_imported(run: Imported, toml_path, *, force: bool = False) -> Path:
    """Write ``run``'s experiment file at ``toml_path`` (its data mapped relative to it);
    never over an existing file unless ``force``. Returns the path."""
    toml_path = Path(toml_path)
    text = run.toml_text(toml_path.parent)
    if toml_path.exists() and not force:
        raise UserError(f"{toml_path} exists; choose another name or pass --force to replace it")
    try:
        toml_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{toml_path}: cannot write it ({exc.strerror or exc})") from None
    # Atomically (a temporary name, then a rename): a full disk leaves no half file.
    return write_text(toml_path, text, force=force)


_SOURCE = re.compile(
    r"(?P<file>.*\.(" + "|".join(x[1:] for x in RAW_SUFFIXES) + r"))(?::(?P<variable>[^:/\\]+))?\Z",
    re.IGNORECASE,
)


def split_source(text) -> tuple[Path, str | None]:
    """(file, variable or None) of "file.mat" or "file.mat:variable" ("scope[1]", "scope[cart
    position]": one signal of a muxed scope; "file.csv:column"); None when ``text`` names no
    raw recording (:data:`RAW_SUFFIXES`)."""
    match = _SOURCE.match(str(text))
    if match is None:
        return None
    return Path(match["file"]), match["variable"]


def _choose(path: Path, signals: list[RawSignal], variable: str) -> list[RawSignal]:
    """``signals`` of ``path`` with ``variable`` (the user's choice) as the position; the
    signals that looked like positions before no longer do."""
    if is_csv(path):
        source = f"{path.name}:{variable}"
        if all(s.source != source for s in signals):
            columns = ", ".join(s.names[0] for s in signals)
            raise UserError(f"{source}: no column {variable!r} (columns: {columns}); choose one")
        return _as_position(signals, source)
    base, selector = matfile.parse_variable(variable)
    try:
        obj = matfile.load_mat(path)[base]
    except KeyError:
        names = sorted({s.source.split(":", 1)[1].split("[")[0] for s in signals})
        raise UserError(
            f"{path.name}:{variable}: no variable {base!r} in {path.name} (variables with "
            f"signals: {', '.join(names) or 'none'}); choose one of them"
        ) from None
    try:
        one = matfile.select_signal(
            matfile.scope_signals(obj, base), selector, f"{path.name}:{base}"
        )
    except matfile.LayoutError as exc:
        raise UserError(str(exc)) from None
    return _as_position(
        signals, f"{path.name}:{base}" + (f"[{one.index}]" if one.count > 1 else "")
    )


CHOSEN = "chosen by the user"


def _as_position(signals: list[RawSignal], source: str) -> list[RawSignal]:
    """``signals`` with the one of ``source`` the position, chosen by the user."""
    out = []
    for s in signals:
        if s.source == source:
            s = dataclasses.replace(s, role="y", why=CHOSEN)
        elif s.role == "y":
            s = dataclasses.replace(s, role="?", why="another signal is the position")
        out.append(s)
    return out


def run_of(path, experiment: str | None = None) -> Imported:
    """The run that the .mat file ``path`` belongs to ("file.mat", or "file.mat:variable" to
    choose the position, e.g. "scope[1]" of a muxed scope), with the files of its folder whose
    names differ only by the signal (2.1pos.mat brings 2.1volt.mat); ``experiment`` names it."""
    path, variable = split_source(path) or (Path(path), None)
    if path.is_dir():
        raise UserError(f"{path}: a folder; give a .mat or .csv file")
    if not path.is_file():
        raise UserError(f"{path}: no such file; give the path of a .mat or .csv file")
    named = {path.name: experiment} if experiment else {}
    chosen = {path.name: variable} if variable else None
    runs = scan([path, *siblings(path)], named=named, chosen=chosen)
    parts = [run for run in runs if path in run.files and run.part is not None]
    if len(parts) > 1:
        listed = "; ".join(
            f"{run.part}: "
            + (run.problem if run.problem else run.anchor.source)
            + ("" if run.experiment is None else f" ({EXPERIMENTS[run.experiment].what})")
            for run in parts
        )
        raise UserError(
            f"{path}: holds {len(parts)} runs ({listed}); give FILE.mat:VARIABLE, the position "
            f"or error of the one you mean, or write an experiment file for each with "
            f"jaxcart import {path.name}"
        )
    for run in runs:
        if path in run.files:
            if experiment and run.guess is not None and not run.guess.named:
                run.guess = recognise(_traces(run), experiment)  # joined through a sibling
            return run
    raise AssertionError("every file is in a run")  # pragma: no cover
