"""A whole class at once (``jaxcart class``): the lab over every student's (or group's) folder,
one table of every handout number, checks against the spec, outliers against the class.

    CLASS_DIR/alice/*.toml ...        --run_class-->   OUT/class.csv, class.html, class.json
    CLASS_DIR/bob/*.toml ...                           OUT/figures/distributions.png, overlays.png
    ...                                                OUT/students/NAME/report.html (the lab's)
                                                       OUT/logs/NAME.log (each lab's progress)

Each student's folder is given to the lab (:func:`tuning.lab.report.run_lab`) in a process of
its own (a pool of ``workers``), and the class reads each report's ``results.json``: nothing of
the lab is computed here. The lab reads a student's folder part by part (``partial``): a file
that cannot be read (a broken data file, an unreadable .mat, a recording lab.toml names that
is not there) costs its part, flagged, and the other parts complete. A folder the lab refuses
as a whole (no recording at all) or a process that dies is one failed row of the table, with
its one-line reason; the others complete.

Compilation is paid once for the class, not once per process: with the compilation cache on,
one student's lab runs alone first (the one with the most files, so the most of the lab's
programs), its programs compiled into the cache, and then the others, ``workers`` at once, in
processes that read them from there.

The table flags, for each student: a part lost to a file that cannot be used, a missing part
(no recording for a slot), an unrecognised file (a file of the folder the lab did not use), and
an outlier: an estimate of a parameter of the cart (a value in kg/s or N, such as B_eq or f_c;
a bound on one, such as the P-control runs' lower bound on f_c, is not judged) at least
:data:`OUTLIER_FACTOR` times the class's median or at most 1/:data:`OUTLIER_FACTOR` of it
(carts of one model differ by tens of percent; a factor of ten is a unit slip or a wrong
recording). Part (v)'s measured step is checked against the handout's specification
(:class:`tuning.design.losses.Spec`: settling in the 2 % band under 1 s, overshoot under 5 %).

>>> result = run_class("class/", "class-report/", workers=2)      # doctest: +SKIP
>>> result.counts()                                                # doctest: +SKIP
{'students': 8, 'complete': 7, 'failed': 1}
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import multiprocessing
import os
import shutil
import statistics
import sys
import time
import tomllib
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hw.jsonio import write_json
from jaxcart import xlaflags
from jaxcart.cache import enable_persistent_cache
from jaxcart.errors import UserError
from jaxcart.parallel import use_cpu_devices
from tuning.design.losses import Spec
from tuning.lab import classfigures, classpage
from tuning.lab.inputs import INDEX_NAME, SLOTS, find_inputs
from tuning.lab.report import output_dir, run_lab, staged

#: A cart parameter this many times the class median (or 1/this of it) is flagged.
OUTLIER_FACTOR = 10.0
#: Units of the cart's parameters, the values compared with the class's median.
PARAMETER_UNITS = ("kg/s", "N")
#: Fewest students with a value for its median to judge outliers.
MIN_FOR_MEDIAN = 3
#: The report folder's default name (./jaxcart-class, -2, ... when it exists).
DEFAULT_OUT = Path("jaxcart-class")
#: Points kept per run for the overlays (runs are thinned evenly).
OVERLAY_POINTS = 1500


@dataclass
class Student:
    """One student's (or group's) lab.

    name: the sub-folder's name; folder: it; status: "complete" or "failed"; error: the
    one-line reason of a failure; seconds: the lab's wall time [s]; cpu_seconds: the CPU time
    its process spent on it [s] (all threads); results: its results.json
    (None when failed); runs: {slot: (time [s], position [m], reference [m] or None)}, thinned,
    for the overlays; used: the files of the folder the lab used; unrecognised: the files it
    did not use, (name, why);
    flags: what the class table flags; checks: {check: True/False/None (not measured)};
    marked: keys of the numbers flagged as outliers or failing the spec.
    """

    name: str
    folder: Path
    status: str = "failed"
    error: str | None = None
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    results: dict | None = None
    runs: dict = field(default_factory=dict)
    used: list = field(default_factory=list)
    unrecognised: list = field(default_factory=list)
    flags: list = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    marked: set = field(default_factory=set)

    @property
    def complete(self) -> bool:
        return self.status == "complete"

    @property
    def report(self) -> str | None:
        """The student's report page, relative to the class folder."""
        return f"students/{self.name}/report.html" if self.complete else None

    @property
    def verdict(self) -> str:
        """ "pass", "fail" or "n/a" (failed lab, or no Part (v) recording) against the spec."""
        if not self.complete or not self.checks:
            return "n/a"
        got = list(self.checks.values())
        if any(v is False for v in got):
            return "fail"
        return "pass" if all(v is True for v in got) else "n/a"

    def value(self, key: str):
        """A number of the report [SI units] (None when absent or not finite)."""
        entry = ((self.results or {}).get("values") or {}).get(key)
        if not isinstance(entry, dict) or not isinstance(entry.get("value"), int | float):
            return None
        x = float(entry["value"])
        return x if math.isfinite(x) else None


@dataclass(frozen=True)
class Column:
    """One handout number of the table: results.json key, label, unit (SI), part, and the
    bound it is ("lower", "upper") when it bounds a quantity instead of estimating it."""

    key: str
    label: str
    unit: str
    part: str
    bound: str | None = None


@dataclass
class ClassResult:
    """The class: its folder, the output folder, the students (sorted by name), the table's
    columns, the columns every complete student shares one value of (``constant``: key ->
    value), the spec checked, the wall time [s] and the number of worker processes."""

    folder: Path
    out: Path
    students: list
    columns: list
    constant: dict
    spec: dict
    seconds: float
    workers: int
    diagnosis: bool
    stray: list = field(default_factory=list)

    def counts(self) -> dict:
        done = sum(s.complete for s in self.students)
        return {"students": len(self.students), "complete": done, "failed": len(self) - done}

    def __len__(self) -> int:
        return len(self.students)

    def varying(self) -> list:
        """The columns whose values differ between students (the table's own columns)."""
        return [c for c in self.columns if c.key not in self.constant]


# ---------------------------------------------------------------- the class's folders


def find_students(folder) -> tuple[list[Student], list[str]]:
    """(the students: one per sub-folder, sorted by name; what belongs to no student: files
    at the top of the class folder, a class report written there). Hidden entries are
    skipped."""
    folder = Path(folder)
    if not folder.is_dir():
        what = "a file, not a folder" if folder.exists() else "no such folder"
        raise UserError(
            f"{folder}: {what}; give the class folder that holds one sub-folder per student"
        )
    entries = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    # A class report written inside the class folder (--out class/report) is no student.
    reports = [p for p in entries if p.is_dir() and (p / "class.csv").is_file()]
    entries = [p for p in entries if p not in reports]
    students = [Student(p.name, p) for p in entries if p.is_dir()]
    if not students:
        raise UserError(
            f"{folder}: no sub-folders; put each student's (or group's) recordings in a "
            f"sub-folder of its own, e.g. {folder}/alice/"
        )
    stray = [p.name for p in entries if not p.is_dir()]
    return students, stray + [f"{p.name}/ (a class report)" for p in reports]


def unrecognised_files(folder: Path, results: dict, used) -> list[tuple[str, str]]:
    """Files at the top of a student's folder that the lab used for no part, with the reason:
    the lab's own (a file it read and gave no part) or "not read by the lab". used: the names
    of the files the lab used (:func:`used_files`)."""
    data = results.get("data") or {}
    reasons = {str(u.get("file")): u.get("reason") for u in data.get("unused") or ()}
    out = []
    for path in sorted(folder.iterdir()):
        if path.name.startswith(".") or path.is_dir() or path.name in used:
            continue
        out.append((path.name, reasons.get(path.name) or "not read by the lab"))
    listed = {name for name, _ in out}
    # What the lab read and left that is no top-level file: a run of several .mat files
    # ("a.mat + b.mat"), a file in a sub-folder.
    out += [(name, why) for name, why in reasons.items() if name not in listed | set(used)]
    return out


def used_files(inputs) -> list[str]:
    """Names of the files the lab's inputs (:func:`tuning.lab.inputs.find_inputs`) used: its
    lab.toml, each recording's experiment file and the data files it maps, the raw .mat files
    of imported runs, and the further runs of a part."""
    used = {INDEX_NAME}
    recordings = list(inputs.recordings.values())
    recordings += [r for runs in inputs.repeats.values() for r in runs]
    for rec in recordings:
        path = Path(rec.path)
        used.add(path.name)
        used.update(_data_files(path))
    raw = [*inputs.imported.values(), *(r for rs in inputs.imported_repeats.values() for r in rs)]
    for run in raw:
        used.update(Path(f).name for f in run.files)
    return sorted(used)


def _data_files(toml: Path) -> set[str]:
    """The data files an experiment file names (data = "x.csv" or a [data] table of
    "file:variable" entries)."""
    if toml.suffix != ".toml" or not toml.is_file():
        return set()
    try:
        meta = tomllib.loads(toml.read_text())
    except (OSError, ValueError):
        return set()
    given = meta.get("data")
    names = [given] if isinstance(given, str) else list((given or {}).values())
    return {Path(str(n).split(":", 1)[0]).name for n in names if isinstance(n, str)}


# ---------------------------------------------------------------- one student's lab


def run_student(folder, out, log, *, diagnosis: bool = False) -> dict:
    """Run the lab on one student's folder into ``out``, its progress into the file ``log``;
    returns {"status", "error", "seconds", "cpu_seconds", "runs", "used"}. Never raises for the
    student's data: a file that cannot be read costs its part (the lab reads the folder
    partially), a refused folder or a failure of the lab is the returned status and its
    one-line reason (a traceback, for an internal error, goes to the log). Runs in a worker
    process."""
    started, cpu = time.perf_counter(), time.process_time()
    outcome = {"status": "failed", "error": None, "runs": {}, "used": []}
    with open(log, "w") as stream, contextlib.redirect_stderr(stream):
        try:
            with contextlib.redirect_stdout(stream):
                run_lab(folder, out, stream=stream, diagnosis=diagnosis, partial=True)
                inputs = find_inputs(folder, partial=True)
                outcome["runs"], outcome["used"] = _runs(inputs), used_files(inputs)
            outcome["status"] = "complete"
        except UserError as exc:
            outcome["error"] = str(exc)
        except Exception as exc:  # noqa: BLE001 - isolated: one student's failure, reported
            traceback.print_exc(file=stream)
            where = f"logs/{Path(log).name}"  # in the class report (written elsewhere first)
            outcome["error"] = f"internal error ({type(exc).__name__}: {exc}); see {where}"
        if outcome["error"]:
            print(f"failed: {outcome['error']}", file=stream)
    outcome["seconds"] = time.perf_counter() - started
    outcome["cpu_seconds"] = time.process_time() - cpu
    return outcome


def _runs(inputs) -> dict:
    """{slot: (time, position, reference or None)} of the recordings, thinned for overlays."""
    runs = {}
    for slot, rec in inputs.recordings.items():
        n = len(rec.position)
        keep = np.unique(np.linspace(0, n - 1, min(n, OVERLAY_POINTS)).astype(int))
        ref = None if rec.reference is None else np.asarray(rec.reference, float)[keep]
        runs[slot] = (np.asarray(rec.time, float)[keep], np.asarray(rec.position, float)[keep], ref)
    return runs


def _start_worker(n_devices: int, cache: bool) -> None:
    """A worker process: jaxcart's XLA setting, the compilation cache and its share of the
    cores as XLA devices, before JAX starts (as ``jaxcart`` sets them for a command)."""
    xlaflags.request()  # loops compiled whole, before jax starts

    if cache:
        enable_persistent_cache()
    use_cpu_devices(n_devices)


def run_all(
    students, out: Path, *, workers: int, diagnosis: bool, cache: bool, say, job=None
) -> None:
    """Every student's lab, ``workers`` at once in processes of their own; fills each
    :class:`Student` and says each completion. With the compilation cache on (``cache``) and
    more than one process, the lab of :func:`lead` runs alone first: it compiles the lab's
    programs into the cache, which the other processes then read instead of each compiling
    them again. A process that dies (crash, out of memory) takes the students it was running
    with it: each is then rerun alone in a fresh process, so only the one that kills its
    process is reported failed. job: what runs in the worker (default :func:`run_student`; a
    module-level function of the same signature)."""
    job = job or run_student
    jobs = {s.name: s for s in students}
    done = [0]

    def finish(student, outcome):
        student.status, student.error = outcome["status"], outcome["error"]
        student.seconds, student.runs = outcome["seconds"], outcome.get("runs") or {}
        student.cpu_seconds = outcome.get("cpu_seconds") or 0.0
        student.used = outcome.get("used") or []
        done[0] += 1
        how = student.error
        if student.complete:
            how = f"complete in {student.seconds:.1f} s ({student.cpu_seconds:.1f} s of CPU)"
        say(f"[{done[0]}/{len(jobs)}] {student.name}: {how}")

    order = list(jobs.values())
    first = []
    if cache and workers > 1 and len(order) > 1:
        first = [lead(order)]
        order.remove(first[0])
        say(f"{first[0].name} first, alone: its lab compiles the class's programs once")
    crashed, waiting = _pool(job, first, order, out, workers, diagnosis, cache, finish)
    if waiting:  # the lead's process died and broke the pool: the others in a new one
        crashed += _pool(job, [], waiting, out, workers, diagnosis, cache, finish)[0]
    for student in crashed:  # alone, each in a fresh process
        lost = _pool(job, [], [student], out, 1, diagnosis, cache, finish)[0]
        if lost:
            _remove_partial(out / "students", student.name)
            finish(
                student,
                {
                    "status": "failed",
                    "error": "its lab process died (a crash or out of memory); see its log",
                    "seconds": 0.0,
                },
            )


def lead(students) -> Student:
    """The student whose lab compiles the most of the class's programs: the one with the most
    files (the most recordings), the first by name among equals."""

    def files(student):
        try:
            return sum(1 for p in student.folder.iterdir() if p.is_file())
        except OSError:
            return 0

    return min(students, key=lambda s: (-files(s), s.name))


def _pool(job, first, students, out, workers, diagnosis, cache, finish) -> tuple[list, list]:
    """Run ``first`` (alone), then ``students``, in one pool of ``workers`` processes;
    returns (those lost to a process that died, those not started because it broke the pool
    while ``first`` ran)."""
    share = max(1, (os.cpu_count() or 1) // workers)
    lost = []
    with ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),  # JAX's threads do not survive fork
        initializer=_start_worker,
        initargs=(share, cache),
    ) as pool:
        for batch in (first, students):
            if lost:  # the pool broke on the first: the others were never started
                return lost, list(batch)
            futures = {
                pool.submit(
                    job,
                    s.folder,
                    out / "students" / s.name,
                    out / "logs" / f"{s.name}.log",
                    diagnosis=diagnosis,
                ): s
                for s in batch
            }
            for future in as_completed(futures):
                student = futures[future]
                try:
                    outcome = future.result()
                except BrokenProcessPool:
                    lost.append(student)
                    continue
                finish(student, outcome)
    return lost, []


def _remove_partial(folder: Path, name: str) -> None:
    for path in folder.glob(f".{name}.partial-*"):
        shutil.rmtree(path, ignore_errors=True)


# ---------------------------------------------------------------- the table


def read_results(students, out: Path) -> None:
    """Each complete student's results.json (a student whose report cannot be read fails)
    and the files of its folder the lab did not use."""
    for s in students:
        if not s.complete:
            continue
        path = out / "students" / s.name / "results.json"
        try:
            s.results = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            s.status, s.error = "failed", f"its report's {path.name} cannot be read ({exc})"
            continue
        # A file the lab could not use is flagged as that (with the data it maps), not as
        # unrecognised.
        broken = {str(b.get("file")) for b in (s.results.get("data") or {}).get("broken") or ()}
        for name in list(broken):
            broken |= _data_files(s.folder / name)
        s.unrecognised = unrecognised_files(s.folder, s.results, [*s.used, *sorted(broken)])


def columns_of(students) -> list[Column]:
    """Every number of the complete students' reports, in the order the lab found them."""
    seen: dict[str, dict] = {}
    for s in students:
        for key, entry in ((s.results or {}).get("values") or {}).items():
            if isinstance(entry, dict):
                first = seen.setdefault(key, {"entry": entry, "labels": set()})
                first["labels"].add(str(entry.get("label", key)))
    return [
        Column(
            key,
            common_label(v["labels"]),
            str(v["entry"].get("unit", "")),
            str(v["entry"].get("part", "")),
            v["entry"].get("bound"),
        )
        for key, v in seen.items()
    ]


def common_label(labels) -> str:
    """One label for a number whose label differs between reports (it names a student's own
    value or file, "B_eq ... with f_c = 0.381 N held"): the words they share, up to the first
    that differs."""
    labels = sorted(labels)
    if len(labels) == 1:
        return labels[0]
    words = []
    for group in zip(*(label.split() for label in labels), strict=False):
        if len(set(group)) > 1:
            break
        words.append(group[0])
    text = " ".join(words).rstrip(" =:,(")
    if text.count("(") > text.count(")"):  # an opened parenthesis cut short
        text = text[: text.rfind("(")].rstrip(" =:,")
    return text or labels[0]


def constant_columns(students, columns) -> dict:
    """{key: value} of the columns every complete student has one and the same value of
    (the pre-lab's numbers on the handout's model): said once, above the table."""
    done = [s for s in students if s.complete]
    out = {}
    for c in columns:
        values = [s.value(c.key) for s in done]
        if (
            len(done) > 1
            and None not in values
            and max(values) - min(values) <= 1e-9 * max(1.0, max(abs(v) for v in values))
        ):
            out[c.key] = values[0]
    return out


def spec_checks(students, spec) -> None:
    """Part (v)'s measured step against the spec: settling time and overshoot, each True,
    False, or None (no Part (v) recording)."""
    for s in students:
        if not s.complete:
            continue
        settling = _measured(s, "pid_measured_settling_time", s.results, "settling_time")
        overshoot = _measured(s, "pid_measured_overshoot", s.results, "overshoot")
        s.checks = {
            "settling": None if settling is None else settling < spec.settling_time,
            "overshoot": None if overshoot is None else overshoot < spec.overshoot,
        }
        if s.checks["settling"] is False:
            s.marked.add("pid_measured_settling_time")
        if s.checks["overshoot"] is False:
            s.marked.add("pid_measured_overshoot")


def _measured(student, key, results, metric):
    """A Part (v) measured metric; a run that never settles counts as infinitely slow."""
    x = student.value(key)
    if x is not None:
        return x
    entry = ((results or {}).get("values") or {}).get(key)
    if isinstance(entry, dict) and entry.get("value") == "inf":
        return math.inf
    return None


def flag(students, columns) -> None:
    """Each student's flags: failure, files that cannot be used (with the part each cost),
    missing parts, unrecognised files, outliers."""
    medians = class_medians(students, columns)
    for s in students:
        s.flags = []
        if not s.complete:
            s.flags.append(f"the lab failed: {s.error}")
            continue
        data = s.results.get("data") or {}
        missing = list(data.get("missing") or ())
        for entry in data.get("broken") or ():
            slot, name, why = entry.get("slot"), entry.get("file"), entry.get("reason")
            if slot in missing:  # the part it was named for has no recording: say so once
                missing.remove(slot)
                part, what = SLOTS[slot]
                s.flags.append(f"Part ({part}) lost: {what}: {name} cannot be used ({why})")
            else:
                s.flags.append(f"file {name} cannot be used ({why})")
        for slot in missing:
            part, what = SLOTS.get(slot, ("?", slot))
            s.flags.append(f"missing Part ({part}): {what}")
        for name, why in s.unrecognised:
            s.flags.append(f"unrecognised file {name} ({why})")
        for c in columns:
            note = outlier(s.value(c.key), medians.get(c.key), c)
            if note:
                s.flags.append(note)
                s.marked.add(c.key)


def class_medians(students, columns) -> dict:
    """{key: the class's median} of the estimates of the cart's parameters (units
    :data:`PARAMETER_UNITS`; a bound on one is no estimate of it: a cart that stopped near its
    target bounds f_c by almost nothing, whatever its f_c) over the complete students that
    have the value (at least :data:`MIN_FOR_MEDIAN`)."""
    out = {}
    for c in columns:
        if c.unit not in PARAMETER_UNITS or c.bound is not None:
            continue
        values = [v for s in students if s.complete and (v := s.value(c.key)) is not None]
        if len(values) >= MIN_FOR_MEDIAN:
            out[c.key] = statistics.median(values)
    return out


def outlier(value, median, column: Column) -> str | None:
    """The flag of a value at least :data:`OUTLIER_FACTOR` times the median, or at most
    1/:data:`OUTLIER_FACTOR` of it, or of the opposite sign; None when in line."""
    if value is None or median is None or median == 0:
        return None
    ratio = value / median
    if 1.0 / OUTLIER_FACTOR < ratio < OUTLIER_FACTOR:
        return None
    return (
        f"outlier: {column.label} = {value:.4g} {column.unit} is {ratio:.3g} x the class "
        f"median {median:.4g} {column.unit}"
    )


# ---------------------------------------------------------------- writing


def csv_text(result: ClassResult) -> str:
    """The table as CSV: one row per student; every handout number in SI units (the unit in
    its header), the spec checks, the flags and the report's path."""
    head = ["student", "status", "spec", "settling < spec", "overshoot < spec", "seconds"]
    head += ["flags", "report", "error"]
    head += [f"{c.key} [{c.unit}]" if c.unit else c.key for c in result.columns]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(head)
    for s in result.students:
        row = [s.name, s.status, s.verdict]
        row += [_yes(s.checks.get("settling")), _yes(s.checks.get("overshoot"))]
        row += [f"{s.seconds:.1f}", "; ".join(s.flags), s.report or "", s.error or ""]
        row += ["" if (v := s.value(c.key)) is None else repr(v) for c in result.columns]
        writer.writerow(row)
    return buffer.getvalue()


def _yes(check) -> str:
    return "" if check is None else ("yes" if check else "no")


def run_class(
    folder,
    out=None,
    *,
    workers: int | None = None,
    diagnosis: bool = False,
    force: bool = False,
    cache: bool = True,
    stream=None,
) -> ClassResult:
    """Run the lab for every student of ``folder`` and write the class's table, page, figures
    and every student's report into ``out`` (default ./jaxcart-class or a numbered one; an
    existing non-empty one only with ``force``). workers: processes at once (default one per
    core, at most one per student); diagnosis: the lab's diagnosis section (most of its time;
    off by default); cache: the compilation cache in the workers; stream: progress (stderr).
    Returns the :class:`ClassResult`."""
    started = time.perf_counter()
    stream = sys.stderr if stream is None else stream

    def say(text):
        print(f"class [{time.perf_counter() - started:6.1f} s] {text}", file=stream, flush=True)

    students, stray = find_students(folder)
    workers = max(1, min(workers or os.cpu_count() or 1, len(students)))
    final = _output(out, force, output_dir)
    say(
        f"{len(students)} students in {folder}, {workers} processes, diagnosis "
        f"{'on' if diagnosis else 'off'}"
    )
    with staged(final) as tmp:
        (tmp / "students").mkdir()
        (tmp / "logs").mkdir()
        run_all(students, tmp, workers=workers, diagnosis=diagnosis, cache=cache, say=say)
        result = _tabulate(folder, final, tmp, students, stray, started, workers, diagnosis)
        _write(result, tmp)
    done = result.counts()
    say(
        f"done: {done['complete']} of {done['students']} complete, {done['failed']} failed, "
        f"in {result.seconds:.1f} s: {final / 'class.html'}, {final / 'class.csv'}"
    )
    return result


def _output(out, force, output_dir) -> Path:
    if out is not None:
        return output_dir(out, force=force)
    path, n = DEFAULT_OUT, 1
    while path.exists():
        n += 1
        path = DEFAULT_OUT.with_name(f"{DEFAULT_OUT.name}-{n}")
    return path


def _tabulate(folder, final, tmp, students, stray, started, workers, diagnosis) -> ClassResult:
    spec = Spec()
    read_results(students, tmp)
    columns = columns_of(students)
    spec_checks(students, spec)
    flag(students, columns)
    return ClassResult(
        folder=Path(folder),
        out=final,
        students=students,
        columns=columns,
        constant=constant_columns(students, columns),
        spec={"settling_time": spec.settling_time, "overshoot": spec.overshoot, "step": spec.step},
        seconds=time.perf_counter() - started,
        workers=workers,
        diagnosis=diagnosis,
        stray=stray,
    )


def _write(result: ClassResult, tmp: Path) -> None:
    figures = classfigures.draw(result, tmp / "figures")
    (tmp / "class.csv").write_text(csv_text(result))
    (tmp / "class.html").write_text(classpage.page(result, figures))
    write_json(tmp / "class.json", to_json(result), force=True)


def to_json(result: ClassResult) -> dict:
    """The class as JSON: per student its status, checks, flags, report and every number."""
    return {
        "folder": str(result.folder),
        "seconds": result.seconds,
        "workers": result.workers,
        "diagnosis": result.diagnosis,
        "spec": result.spec,
        "counts": result.counts(),
        "not_student_folders": result.stray,
        "units": {c.key: c.unit for c in result.columns},
        "students": {
            s.name: {
                "status": s.status,
                "error": s.error,
                "seconds": s.seconds,
                "cpu_seconds": s.cpu_seconds,
                "spec": s.verdict,
                "checks": s.checks,
                "flags": s.flags,
                "report": s.report,
                "values": {c.key: s.value(c.key) for c in result.columns},
            }
            for s in result.students
        },
    }
