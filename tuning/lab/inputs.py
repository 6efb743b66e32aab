"""Which recording is which part of the lab.

A data folder holds experiment files (the format of docs/experiment-files.md). Each is given
a *slot* of the lab:

    slot      part   what it is                                   how it is recognised
    tap       (i)    tap test, motor unplugged                    kind = "tap"
    p_step    (ii)   P control k = 50 V/m, step 0.4 m             closed loop, ki = kd = 0, kp != 10
    ramp      (iii)  open-loop voltage ramp 0.1 V/s               kind = "open_loop", ramp input
    p_error   (iii)  P control k = 10 V/m, step (e(inf) bound)    closed loop, ki = kd = 0, kp = 10
    pi        (iv)   PI control k = 10, k_i = 15                  closed loop, ki > 0, kd = 0
    pid       (v)    PID design, step                             closed loop, kd > 0

The folder may also hold raw .mat files as QUARC/Simulink scopes saved them, without any
TOML: each run (a file, or files whose names differ only by the signal, "2.1pos.mat" +
"2.1volt.mat") is recognised from its content and names (:mod:`jaxcart.recognition`), with
its evidence; so is a CSV file of named columns that no experiment file maps (another
simulator's "time,position,voltage"; a CSV that is no such table is listed unused, not an
error); a run whose evidence is weak is left out with one line that asks the user to
name its part, and a second run of a part is a repeat (the experiment file's, else the first
by name, is the part's). When any recording came from raw .mat files, :func:`write_used` writes the
lab.toml and the experiment files that were used beside the report, so that a user can correct
one line and rerun (``jaxcart lab --data REPORT_DIR``).

An optional index ``lab.toml`` in the folder names the files and wins over the guess:

    [recordings]
    tap = "tap.toml"
    p_step = "p50.toml"
    pi = "run7.mat"                            # a raw .mat file: this part, no guess
    p_error = ["p10pos.mat", "p10err.mat"]     # the .mat files of one run

and may carry a ``[synthetic]`` table: the true parameters that generated synthetic data (the
built-in example recordings use it; the report prints it and compares the fits with it).

What ``jaxcart simulate`` wrote (in the folder or below it: its description says so) is a
simulation, never a run of the cart: it is listed as not used.

A file that cannot be read (a broken data file, an unreadable .mat, a recording lab.toml names
that is not there) refuses the lab with its one line, so that ``jaxcart lab`` says what to fix.
With ``partial=True`` (``jaxcart class``: one student's broken file must not cost the whole lab)
it costs only its part instead: the file is listed in ``Inputs.broken`` with the reason, its
part has no recording (simulation only) and every other part is computed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hw.expfile import ExpFileError, is_simulation, read_toml, toml_str, toml_value
from jaxcart.errors import UserError
from jaxcart.files import read_experiment, read_imported
from jaxcart.matimport import (
    RAW_SUFFIXES,
    data_prefix,
    files_of,
    read_signals,
    scan,
    split_source,
)
from jaxcart.params import TRACK_LENGTH
from jaxcart.plausibility import check_integral_start, time_unit_doubt, warn
from jaxcart.recognition import EXPERIMENTS
from tuning.estimation.diagnose.controller import check as controller_check

INDEX_NAME = "lab.toml"
#: The sub-folder of a report where :func:`write_used` puts the experiment files of repeats.
REPEAT_FOLDER = "repeat"

#: slot -> (handout part, what the recording is)
SLOTS = {
    "tap": ("i", "tap test, motor unplugged"),
    "p_step": ("ii", "P control, k = 50 V/m, step of 0.4 m"),
    "ramp": ("iii", "open-loop voltage ramp, 0.1 V/s"),
    "p_error": ("iii", "P control, k = 10 V/m, step (steady-state error)"),
    "pi": ("iv", "PI control, k = 10 V/m, k_i = 15 V/(m s), step"),
    "pid": ("v", "PID design, step"),
}
#: The P gain [V/m] of Part (iii)'s steady-state-error experiment.
K_ERROR = 10.0


@dataclass
class Inputs:
    """The recordings found for the lab.

    folder: the data folder; recordings: slot -> Recording (jaxcart.files); how: slot -> how
    it was chosen ("lab.toml" or the rule that matched); unused: (file name, reason) of files
    that went to no slot; synthetic: the [synthetic] table of lab.toml (true parameters of
    synthetic data) or None; imported: slot -> the :class:`jaxcart.matimport.Imported` run of
    raw .mat files that the slot's recording came from; offers: (slot, run, why) of raw runs
    not used (a second run of a part, weak evidence), offered in the lab.toml written;
    written: what :func:`write_used` wrote, one line; repeats: slot -> further runs of that
    part (more files of it, raw .mat runs recognised as it, or files in a sub-folder such as
    ``repeat/``): the cart's joint fit uses them, and the report shows them;
    imported_repeats: slot -> the raw .mat runs among them; broken: (file name, the slot
    lab.toml named it for or None, why it cannot be used) of the files a partial read left
    out; partial: such files cost their part instead of the lab.
    """

    folder: Path | None
    recordings: dict = field(default_factory=dict)
    how: dict = field(default_factory=dict)
    unused: list = field(default_factory=list)
    synthetic: dict | None = None
    imported: dict = field(default_factory=dict)
    offers: list = field(default_factory=list)
    written: str | None = None
    repeats: dict = field(default_factory=dict)
    imported_repeats: dict = field(default_factory=dict)
    broken: list = field(default_factory=list)
    partial: bool = False

    @contextlib.contextmanager
    def reading(self, name: str, slot: str | None = None):
        """Read the file ``name`` (for ``slot`` when lab.toml names it) inside this block: a
        :class:`UserError` refuses the lab, or, partial, lists the file as broken and ends only
        the block."""
        try:
            yield
        except UserError as exc:
            if not self.partial:
                raise
            why = _without_folder(str(exc), self.folder)
            self.broken.append((name, slot, why.removeprefix(f"{name}: ")))

    def runs(self) -> list:
        """Every recording of the lab: each part's, then the repeats (the joint fit's input)."""
        return list(self.recordings.values()) + [r for rs in self.repeats.values() for r in rs]

    def missing(self) -> list[str]:
        """Slots with no recording (their parts show simulation only)."""
        return [s for s in SLOTS if s not in self.recordings]

    def summary_lines(self) -> list[str]:
        """One line per slot: which file went to which part, or that none did."""
        lines = []
        for slot, (part, what) in SLOTS.items():
            rec = self.recordings.get(slot)
            if rec is None:
                lines.append(f"Part ({part}) {what}: no recording (simulation only)")
            elif slot in self.imported:
                run = self.imported[slot]
                lines.append(f"Part ({part}) {what}: {run.label} ({self.how[slot]})")
                lines += [f"    {e.line()}" for e in run.guess.evidence]
            else:
                lines.append(f"Part ({part}) {what}: {Path(rec.path).name} ({self.how[slot]})")
            for again in self.repeats.get(slot, []):
                lines.append(f"    and a repeat: {_shown(again, self.folder)}")
                run = next(
                    (r for r in self.imported_repeats.get(slot, []) if r.name == again.path),
                    None,
                )
                lines += [f"      {e.line()}" for e in run.guess.evidence] if run else []
        for name, reason in self.unused:
            lines.append(f"not used: {name} ({reason})")
        for name, slot, reason in self.broken:
            part = f" (Part ({SLOTS[slot][0]}) in {INDEX_NAME})" if slot in SLOTS else ""
            lines.append(f"cannot be used: {name}{part}: {reason}")
        if self.written:
            lines.append(self.written)
        return lines


def _without_folder(text: str, folder) -> str:
    """A message about a file of the data folder, the folder's path left out."""
    if folder is None:
        return text
    return text.replace(f"{Path(folder)}/", "").replace(str(Path(folder)), "the data folder")


def _read_experiment(path):
    return check_recording(read_experiment(path))


def check_recording(recording):
    """The lab's own sanity check of a recording before any part computes with it (the file
    readers check the format): finite positions that fit on the track, a time base in
    seconds (a tap in ms otherwise ends its part with a symptom: "B_eq cannot be determined").
    Returns it."""
    y = np.asarray(recording.position, dtype=float)
    name = recording.path
    if y.size < 2 or not np.all(np.isfinite(y)):
        raise UserError(
            f"{name}: column y needs at least two finite positions [m]; fix the data file"
        )
    span = float(np.ptp(y))
    if span > TRACK_LENGTH:
        unit = " (recorded in mm? divide y by 1000)" if span > 100 * TRACK_LENGTH else ""
        raise UserError(
            f"{name}: the positions y span {span:.4g} m, more than the {TRACK_LENGTH:g} m "
            f"track{unit}; give y in metres"
        )
    doubt = time_unit_doubt(recording)
    if doubt is not None:
        raise UserError(f"{name}: {doubt}")
    return _controller_that_ran(recording)


def _controller_that_ran(recording):
    """``recording`` with the controller its recorded command shows where the file's
    [controller] does not reproduce that command and the one inferred from it does (as the
    diagnosis does, :func:`tuning.estimation.diagnose.controller.check`): a P 50 run filed
    with kp = 5 is simulated with kp = 50, and the lab says so."""
    checked = controller_check(recording)
    if not checked or checked["consistent"] or checked.get("inferred") is None:
        return recording
    span = max(float(np.ptp(np.asarray(recording.command, dtype=float))), 1e-9)
    if checked["inferred_rms"] > 0.02 * span + 1e-3:  # the inferred one does no better
        return recording
    ran, filed = checked["inferred"], recording.controller
    warn(
        f"{recording.path}: the lab uses the controller the recorded command shows (kp = "
        f"{ran.kp:.4g}, ki = {ran.ki:.4g}, kd = {ran.kd:.4g}), not the file's (kp = "
        f"{float(filed.kp):g}, ki = {float(filed.ki):g}, kd = {float(filed.kd):g}); correct "
        "[controller] if the file's is the one that ran"
    )
    return dataclasses.replace(recording, controller=ran)


def _load_toml(path: Path) -> dict:
    if path.is_dir():
        raise UserError(f"{path}: a folder, not an experiment file; rename or move it away")

    try:  # the experiment files' own reader: UTF-16, a BOM, a workbook said with the fix
        return read_toml(path)
    except ExpFileError as exc:
        raise UserError(f"{exc}; or move it out of the folder") from None


def _not_a_recording(meta: dict) -> str:
    """Why an experiment file of the folder is no recording of the cart."""
    if "kind" not in meta:
        return "not an experiment file (no kind)"
    return f"a simulation ({meta.get('description')}), not a recording of the cart"


def guess_slot(recording) -> tuple[str | None, str]:
    """(slot or None, the reason) for one recording, from its kind, controller and input."""
    kind = recording.kind
    if kind == "tap":
        return "tap", "kind = tap"
    if kind == "open_loop":
        inp = (recording.meta or {}).get("input", {})
        if inp.get("kind") == "ramp" or _is_ramp(recording.command):
            return "ramp", "open-loop voltage ramp"
        return None, "open-loop input that is not a ramp"
    ctl = recording.controller
    if ctl is None:
        return None, "closed loop without a [controller] table"
    kp, ki, kd = float(ctl.kp), float(ctl.ki), float(ctl.kd)
    if not _is_step(recording):
        return None, "closed-loop reference that is not a step"
    if kd > 0:
        return "pid", f"PID (kd = {kd:g} > 0), step"
    if ki > 0:
        return "pi", f"PI (ki = {ki:g} > 0, kd = 0), step"
    if math.isclose(kp, K_ERROR, rel_tol=1e-9):
        return "p_error", f"P only with kp = {kp:g} V/m, step"
    return "p_step", f"P only (kp = {kp:g} V/m, ki = kd = 0), step"


def _is_step(recording) -> bool:
    r = recording.reference
    if r is None:
        return False
    r = np.asarray(r, dtype=float)
    return r.size > 1 and float(np.ptp(r[1:])) <= 1e-12 * max(1.0, float(np.abs(r).max()))


def _is_ramp(u) -> bool:
    if u is None:
        return False
    u = np.asarray(u, dtype=float)
    if u.size < 10:
        return False
    slope = np.diff(u)
    return bool(np.all(slope >= 0) and u[-1] > u[0])


def find_inputs(folder, *, partial: bool = False) -> Inputs:
    """Read every experiment file of ``folder`` and give each its slot (lab.toml first), then
    recognise the runs of the raw .mat files that no experiment file maps. partial: a file
    that cannot be read costs its part, listed in ``broken``, instead of refusing the lab."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise UserError(
            f"--data {folder}: a file, not a folder; give the folder that holds the experiment "
            f"files (TOML + data)"
        )
    if not folder.is_dir():
        raise UserError(
            f"--data {folder}: no such folder; give a folder of experiment files (TOML + data)"
        )
    inputs = Inputs(folder=folder, partial=partial)
    index_path = folder / INDEX_NAME
    named, named_raw = {}, {}
    with inputs.reading(INDEX_NAME):
        named, named_raw = _read_index(inputs, index_path)
    for slot, path in named.items():
        with inputs.reading(path.name, slot):
            inputs.recordings[slot] = _read_experiment(path)
            inputs.how[slot] = f"named in {INDEX_NAME}"
    for slot, (paths, chosen) in named_raw.items():
        with inputs.reading(" + ".join(p.name for p in paths), slot):
            _use_raw(inputs, slot, paths, index_path, chosen)

    taken = {p.resolve() for p in named.values()}
    mapped = {p.resolve() for paths, _ in named_raw.values() for p in paths}
    guesses: dict[str, list] = {}
    candidates = sorted(p for p in folder.glob("*.toml") if p.name != INDEX_NAME)
    for path in candidates:
        if path.is_dir():
            inputs.unused.append((path.name, "a folder, not an experiment file"))
            continue
        if path.resolve() in taken:  # read as the part lab.toml names (or said broken there)
            with contextlib.suppress(UserError):
                mapped |= _raw_files(_load_toml(path), folder)
            continue
        recording = None
        with inputs.reading(path.name):
            meta = _load_toml(path)
            mapped |= _raw_files(meta, folder)
            if "kind" not in meta or is_simulation(meta):
                inputs.unused.append((path.name, _not_a_recording(meta)))
                continue
            recording = _read_experiment(path)
        if recording is None:
            continue
        slot, reason = guess_slot(recording)
        if slot is None:
            inputs.unused.append((path.name, reason))
        elif slot in inputs.recordings:
            inputs.unused.append((path.name, f"{slot} is named in {INDEX_NAME}"))
        else:
            guesses.setdefault(slot, []).append((recording, reason))

    for slot, found in guesses.items():
        # Several runs of one part: the first (by name) is the part's, the others repeats.
        inputs.recordings[slot], reason = found[0]
        inputs.how[slot] = f"guessed: {reason}"
        if len(found) > 1:
            inputs.how[slot] += f"; the first of {len(found)} runs of it (name one in {INDEX_NAME})"
        for rec, _ in found[1:]:
            _add_repeat(inputs, slot, rec)
    raw = [p for p in files_of(folder) if p.resolve() not in mapped]
    _recognise_raw(inputs, raw + _raw_csv_files(inputs, folder, mapped))
    if inputs.recordings:  # (the raw files' parts too: a subfolder's run repeats them)
        _repeats_in_subfolders(inputs, folder)
    if not inputs.recordings and inputs.broken:
        raise UserError(
            f"--data {folder}: no recording can be used: "
            + "; ".join(f"{name}: {why}" for name, _, why in inputs.broken)
        )
    if not inputs.recordings:
        below = sorted(str(p.relative_to(folder)) for p in folder.glob("*/*.toml"))[:3]
        where = (
            f"; its sub-folders hold {', '.join(below)}: give --data the folder of one cart's "
            f"runs, or run `jaxcart class {folder}` for a folder of students' folders"
            if below
            else ""
        )
        if inputs.unused:  # files found, none usable: say why each is not (not "none found")
            raise UserError(
                f"--data {folder}: no recording can be used: "
                + "; ".join(
                    f"{name}: {why.removeprefix(name + ': ')}" for name, why in inputs.unused
                )
            )
        raise UserError(
            f'--data {folder}: no experiment files found (TOML files with kind = "tap", '
            f'"open_loop" or "closed_loop", or .mat files saved by the lab\'s scopes); see '
            f"docs/experiment-files.md for the format{where}"
        )
    return inputs


def _shown(recording, folder) -> str:
    """A recording's file, relative to the data folder where it is inside it."""
    path = Path(recording.path)
    try:
        return str(path.relative_to(folder)) if folder is not None else path.name
    except ValueError:
        return path.name


def _same_samples(a, b) -> bool:
    """The same recorded positions (a file given twice, or a copy of it)."""
    ya, yb = np.asarray(a.position, dtype=float), np.asarray(b.position, dtype=float)
    return ya.shape == yb.shape and bool(np.array_equal(ya, yb))


def _add_repeat(inputs: Inputs, slot: str, recording) -> bool:
    """A further run of ``slot``; a copy of a run already used is not a repeat (False)."""
    for other in [inputs.recordings[slot], *inputs.repeats.get(slot, [])]:
        if _same_samples(recording, other):
            name = _shown(recording, inputs.folder)
            same = _shown(other, inputs.folder)
            inputs.unused.append((name, f"the same samples as {same}: not a second run"))
            return False
    inputs.repeats.setdefault(slot, []).append(recording)
    return True


def _repeats_in_subfolders(inputs: Inputs, folder: Path) -> None:
    """Experiment files one folder down: further runs of a part this folder has
    (``repeat/p50_repeat.toml``: the cart's joint fit and the report use them too), or the
    run of a part it has none of (``pd/pd.toml``: Part (v)'s recording; of several, the first
    by path, the others its repeats). (A folder of student sub-folders holds no experiment
    file itself: that is ``jaxcart class``.)"""
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for path in sorted(sub.glob("*.toml")):
            try:
                meta = _load_toml(path)
            except UserError:
                continue
            if "kind" not in meta:
                continue
            if is_simulation(meta):
                inputs.unused.append((str(path.relative_to(folder)), _not_a_recording(meta)))
                continue
            recording = None
            with inputs.reading(str(path.relative_to(folder))):
                recording = _read_experiment(path)
            if recording is None:
                continue
            slot, reason = guess_slot(recording)
            where = str(path.relative_to(folder))
            if slot in inputs.recordings:
                _add_repeat(inputs, slot, recording)
            elif slot is not None:
                inputs.recordings[slot] = recording
                inputs.how[slot] = f"guessed: {reason}; from {sub.name}/ (the only run of it)"
            else:
                inputs.unused.append((where, reason))


def _read_index(inputs: Inputs, index_path: Path) -> tuple[dict, dict]:
    """({slot: experiment file}, {slot: [raw .mat (or CSV) files of one run]}) named in
    lab.toml (and its [synthetic] table into ``inputs``); ({}, {}) without one."""
    named, named_raw = {}, {}
    if not index_path.is_file():
        return named, named_raw
    index = _load_toml(index_path)
    table = index.get("recordings", {})
    if not isinstance(table, dict):
        raise UserError(f'{index_path}: [recordings] must be a table of slot = "file.toml"')
    for slot, name in table.items():
        names = name if isinstance(name, list) else [name]
        # Each entry on its own: a partial read loses only the part of an entry it cannot use.
        with inputs.reading(", ".join(map(str, names)), slot if slot in SLOTS else None):
            paths = _named_paths(index_path, slot, names)
            if all(p.suffix.lower() in RAW_SUFFIXES for p in paths):
                chosen = {p.name: v for p, n in zip(paths, names, strict=True)
                          for v in [(split_source(n) or (None, None))[1]] if v}  # fmt: skip
                named_raw[slot] = (paths, chosen)
            elif len(paths) == 1:
                named[slot] = paths[0]
            else:
                raise UserError(
                    f"{index_path}: [recordings] {slot} = {name!r}: a list names the .mat files "
                    f'of one run; name an experiment file as {slot} = "file.toml"'
                )
    synthetic = index.get("synthetic")
    inputs.synthetic = dict(synthetic) if isinstance(synthetic, dict) else None
    return named, named_raw


def _named_paths(index_path: Path, slot: str, names: list) -> list[Path]:
    """The files one entry of lab.toml's [recordings] names, each checked to be there."""
    folder = index_path.parent
    if slot not in SLOTS:
        raise UserError(
            f"{index_path}: [recordings] {slot} is not a slot of the lab; use one of "
            f"{', '.join(SLOTS)}"
        )
    # "run.mat:y": the run of a workspace that holds several (matimport.runs_in), by its
    # position or error; the file is checked, the variable when the run is read.
    paths = [folder / (split_source(n) or (str(n), None))[0] for n in names]
    for n, path in zip(names, paths, strict=True):
        if path.is_dir():
            raise UserError(
                f"{index_path}: [recordings] {slot} = {n!r} is a folder; name the "
                f"experiment file (TOML) inside it"
            )
        if not path.is_file():
            raise UserError(f"{index_path}: [recordings] {slot} = {n!r}: no such file in {folder}")
    return paths


def _raw_files(meta: dict, folder: Path) -> set:
    """The data files (resolved: .mat, CSV) that an experiment file's data maps."""
    data = meta.get("data")
    sources = data.values() if isinstance(data, dict) else [data]
    out = set()
    for source in sources:
        found = split_source(source) or (Path(str(source)), None)
        out.add((folder / found[0]).resolve())
    return out


def _raw_csv_files(inputs: Inputs, folder: Path, mapped: set) -> list[Path]:
    """The CSV (and .tsv) files of ``folder`` that no experiment file maps and that read as a
    table of named columns (another simulator's recordings); any other is listed unused, with
    why, and does not stop the lab. (A .txt file is read where lab.toml names it: in a folder
    it is more often notes.)"""
    out = []
    for path in files_of(folder, (".csv", ".tsv")):
        if path.resolve() in mapped:
            continue
        try:
            read_signals(path)
        except UserError as exc:
            inputs.unused.append((path.name, f"not a recording ({exc})"))
            continue
        out.append(path)
    return out


def _use_raw(inputs: Inputs, slot: str, paths: list, index_path: Path, chosen: dict) -> None:
    """The raw .mat run ``paths`` named as ``slot`` in lab.toml, read as that experiment
    (``chosen``: {file name: variable}, the run of a file that holds several)."""
    named = {p.name: slot for p in paths}
    runs = scan(paths, named=named, chosen=chosen, one_run=True)
    runs = [r for r in runs if paths[0] in r.files]
    run = runs[0]
    if run.problem or len(run.files) != len(paths):
        why = run.problem or f"its files are not one run ({', '.join(p.name for p in paths)})"
        raise UserError(f"{index_path}: [recordings] {slot}: {why}")
    inputs.recordings[slot] = check_recording(read_imported(run, quiet=True))
    inputs.imported[slot] = run
    inputs.how[slot] = f"named in {INDEX_NAME}"


def _recognise_raw(inputs: Inputs, paths: list) -> None:
    """Give each run of the raw .mat files ``paths`` the part it is recognised as, when the
    evidence is strong and the part is free; the rest go to ``unused`` (and ``offers``) with
    the reason, a question where the evidence is weak."""
    if not paths:
        return

    for run in sorted(_scan(inputs, paths), key=lambda r: r.label):
        guess = run.guess
        if run.problem:
            inputs.unused.append((run.label, run.problem))
            continue
        if not run.usable():
            offered = [s for s in guess.candidates() if s in SLOTS]
            example = (offered or ["p_step"])[0]
            name = run.name.name  # FILE.mat:VARIABLE for one of a workspace's runs
            how = f'in {INDEX_NAME}, e.g. [recordings] {example} = "{name}"'
            inputs.unused.append((run.label, guess.question(run.label, how)))
            inputs.offers += [(s, run, "weak evidence") for s in offered]
            continue
        slot = guess.experiment
        if slot not in SLOTS:
            spec = EXPERIMENTS[slot]
            inputs.unused.append((run.label, f"{spec.what}: no part of the report uses it"))
            continue
        if inputs.how.get(slot) == f"named in {INDEX_NAME}":
            inputs.unused.append(
                (
                    run.label,
                    f"also Part ({SLOTS[slot][0]}) {SLOTS[slot][1]}, but {slot} is named in "
                    f"{INDEX_NAME}",
                )
            )
            inputs.offers.append((slot, run, "another run of this part"))
            continue
        recording = None  # a file that cannot be read, partial: its part is lost, said so
        with inputs.reading(run.label):
            recording = check_recording(read_imported(run, quiet=True))
        if recording is None:
            continue
        late = check_integral_start(run.label, recording)
        if late:  # its integral unknown at the first sample: a model of it would be wrong
            why = late[0].removeprefix(f"{run.label}: ")
            why += f"; to use it anyway, name it in {INDEX_NAME}"
            inputs.unused.append((run.label, why))
            inputs.offers.append((slot, run, "a run that may have started late"))
            continue
        if slot not in inputs.recordings:
            inputs.recordings[slot] = recording
            inputs.imported[slot] = run
            inputs.how[slot] = "recognised, strong evidence"
        elif _add_repeat(inputs, slot, recording):
            # A second run of the part: the experiment file, else the first raw run by name,
            # stays the part's; this one joins the cart's joint fit.
            inputs.imported_repeats.setdefault(slot, []).append(run)
            first = "the first by name" if slot in inputs.imported else "an experiment file"
            inputs.how[slot] += (
                f"; chosen over {run.label} as {first}, which is a repeat the cart's joint "
                f"fit also uses; name another in {INDEX_NAME} to swap"
            )
            inputs.offers.append((slot, run, "another run of this part, used as a repeat"))


def _scan(inputs: Inputs, paths: list) -> list:
    """The runs of the raw .mat files ``paths`` (:func:`jaxcart.matimport.scan`, which refuses
    them all for one file that does not load); partial, such a file is said broken and the
    others are scanned."""
    try:
        return scan(paths)
    except UserError:
        if not inputs.partial:
            raise
    readable = []
    for path in paths:  # which one: each read once more, only on this path
        with inputs.reading(path.name):
            read_signals(path)
            readable.append(path)
    return scan(readable) if readable else []


def write_used(inputs: Inputs, out, final=None) -> list[Path]:
    """When any recording came from raw .mat files: write ``lab.toml`` naming the recording of
    every part, and an experiment file for each raw run used, into ``out`` (the report's
    folder; paths are written relative to ``final``, where it will be, default ``out``), so
    that ``jaxcart lab --data FINAL`` reruns the same lab and a user can correct one line.
    Raw runs not used are offered as commented lines. Returns the paths written."""
    if not inputs.imported:
        return []

    out, final = Path(out), Path(final or out)
    written, names = [], {INDEX_NAME, "results.toml", "gains.toml"}
    lines = [
        "# The lab's recordings, as jaxcart lab used them for the report in this folder (data",
        f"# from {Path(inputs.folder).resolve()}). Correct a line and rerun:",
        f"#     jaxcart lab --data {final} --out NEW_REPORT",
        "[recordings]",
    ]
    for slot, (part, what) in SLOTS.items():
        if slot in inputs.imported:
            run = inputs.imported[slot]
            name = _free_name(run.stem, names)
            written.append(out / name)
            (out / name).write_text(run.toml_text(final))
            lines.append(f"{slot} = {toml_str(name)}   # Part ({part}): {run.label}")
        elif slot in inputs.recordings:
            path = Path(inputs.recordings[slot].path)
            name = data_prefix(final, path.parent) + path.name
            lines.append(f"{slot} = {toml_str(name)}   # Part ({part})")
        else:
            lines.append(f"# {slot} = ...   # Part ({part}) {what}: no recording")
    for slot, runs in inputs.imported_repeats.items():
        written += _write_repeats(out, final, slot, runs, lines)
    for slot, run, why in inputs.offers:
        files = [data_prefix(final, p.parent) + p.name for p in run.files]
        if run.part is not None:  # one of a workspace's runs: FILE.mat:VARIABLE
            files = [data_prefix(final, run.name.parent) + run.name.name]
        value = (
            toml_str(files[0]) if len(files) == 1 else "[" + ", ".join(map(toml_str, files)) + "]"
        )
        lines.append(f"# {slot} = {value}   # {why}: uncomment to use it (and remove the other)")
    if inputs.synthetic:
        lines += ["", "[synthetic]"]
        lines += [f"{k} = {toml_value(v)}" for k, v in inputs.synthetic.items()]
    (out / INDEX_NAME).write_text("\n".join(lines) + "\n")
    written.insert(0, out / INDEX_NAME)
    inputs.written = (
        f"wrote {final / INDEX_NAME} and {len(written) - 1} experiment file(s) beside the "
        f"report: correct a line there and rerun with jaxcart lab --data {final}"
    )
    return written


def _write_repeats(out: Path, final: Path, slot: str, runs: list, lines: list) -> list[Path]:
    """The experiment files of the raw runs that repeat ``slot``, in ``out/repeat/`` (a
    sub-folder's runs of a part are its repeats when the lab reads the folder again), each
    named in a comment of ``lines``. Returns their paths."""
    folder, names, written = out / REPEAT_FOLDER, set(), []
    folder.mkdir(exist_ok=True)
    for run in runs:
        name = _free_name(run.stem, names)
        (folder / name).write_text(run.toml_text(final / REPEAT_FOLDER))
        written.append(folder / name)
        part = SLOTS[slot][0]
        lines.append(f"# {REPEAT_FOLDER}/{name}: {run.label}, a further run of Part ({part})")
    return written


def _free_name(stem: str, used: set) -> str:
    name, k = f"{stem}.toml", 2
    while name in used:
        name, k = f"{stem}-{k}.toml", k + 1
    used.add(name)
    return name
