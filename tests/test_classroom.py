"""`jaxcart class` (tuning/lab/classroom.py, tuning/commands/classroom.py): the lab over a class
of synthetic students made by the repository's generator (tuning/lab/classdata.py), one with
broken files (each costs its part only), one missing a part, one with a stray file, one with
no recording at all (its lab fails, alone); the table, page, figures and links; outliers
against the class's median, on estimates only; a worker process that dies takes no one else
with it; the lead student's lab runs first, alone, so that the class compiles once.
"""

import csv
import json
import os
import time
from pathlib import Path

import pytest

from tuning.lab import classdata, classroom
from tuning.lab.classroom import Column, Student

#: Five: the broken, the missing and the stray student and two plain ones, so that complete
#: labs give the class's medians (classroom.MIN_FOR_MEDIAN is 3); each lab is a whole lab run.
#: A sixth folder, EMPTY, holds no recording: its lab fails at once.
N_STUDENTS = 5
BROKEN, MISSING, STRAY, EMPTY = "student-05", "student-04", "student-03", "student-06"


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """A class of N_STUDENTS (short horizons), run once through the command: (class dir, out, carts,
    exit status, stdout, seconds)."""
    from tuning.commands.main import main

    root = tmp_path_factory.mktemp("class")
    folder = root / "class"
    carts = classdata.generate_class(folder, N_STUDENTS, seed=3, horizons=classdata.SHORT)
    # Broken: a position that is not a number (Part (i)'s tap), a .mat that is not one (a
    # stray scope file), the PI step lab.toml names deleted (Part (iv)). Missing: no ramp
    # (Part (iii)), unnamed. Stray: notes. Empty: nothing to run.
    tap = folder / BROKEN / "tap.csv"
    lines = tap.read_text().splitlines()
    lines[4] = lines[4].split(",")[0] + ",abc"
    tap.write_text("\n".join(lines) + "\n")
    (folder / BROKEN / "pid_scope.mat").write_bytes(b"MATLAB 5.0? no: " + bytes(range(256)))
    for suffix in (".toml", ".csv"):
        (folder / BROKEN / f"pi{suffix}").unlink()
    (folder / EMPTY).mkdir()
    for suffix in (".toml", ".csv"):
        (folder / MISSING / f"ramp{suffix}").unlink()
    index = folder / MISSING / "lab.toml"
    index.write_text("".join(x for x in index.read_text().splitlines(True) if "ramp" not in x))
    (folder / STRAY / "notes.txt").write_text("cart 7, track dusty\n")
    (folder / "roster.csv").write_text("name\n")
    out = root / "report"
    started = time.perf_counter()
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        status = main(["class", str(folder), "--out", str(out), "--workers", "2"])
    seconds = time.perf_counter() - started
    print(f"class of {N_STUDENTS} in {seconds:.1f} s")  # the class run's time (pytest -s)
    return folder, out, carts, status, buffer.getvalue(), seconds


def _rows(out):
    with open(out / "class.csv", newline="") as f:
        return {row["student"]: row for row in csv.DictReader(f)}


def test_the_table_has_every_student_with_failures_isolated(ran):
    folder, out, carts, status, stdout, _ = ran
    assert status == 0
    rows = _rows(out)
    assert sorted(rows) == sorted([*carts, EMPTY])
    assert rows[EMPTY]["status"] == "failed" and "no experiment files" in rows[EMPTY]["error"]
    complete = [n for n, r in rows.items() if r["status"] == "complete"]
    assert sorted(complete) == sorted(carts)
    assert f"{N_STUDENTS + 1} students: {N_STUDENTS} complete, 1 failed" in stdout
    for name in complete:  # each complete student's own report, linked
        assert rows[name]["report"] == f"students/{name}/report.html"
        assert (out / rows[name]["report"]).is_file()
    assert "roster.csv" in json.loads((out / "class.json").read_text())["not_student_folders"]


def test_missing_part_and_stray_file_are_flagged(ran):
    _, out, _, _, stdout, _ = ran
    rows = _rows(out)
    assert "missing Part (iii): open-loop voltage ramp" in rows[MISSING]["flags"]
    assert rows[MISSING]["f_c_ramp_fit [N]"] == ""
    assert "unrecognised file notes.txt" in rows[STRAY]["flags"]
    assert "the lab failed" in rows[EMPTY]["flags"]
    for name, row in rows.items():
        if name not in (MISSING, STRAY, BROKEN, EMPTY):
            assert row["flags"] == "", (name, row["flags"])
    assert f"{MISSING}: missing Part (iii)" in stdout


def test_a_broken_or_missing_file_costs_its_part_not_the_lab(ran):
    """The broken student: a garbage .mat, a tap whose data has a word for a number and a PI
    recording lab.toml names but the folder lacks. Each is flagged with the part it cost; the
    lab completes and Parts (ii), (iii) and (v) recover the student's own cart."""
    _, out, carts, _, stdout, _ = ran
    row = _rows(out)[BROKEN]
    assert row["status"] == "complete" and row["error"] == ""
    flags = json.loads((out / "class.json").read_text())["students"][BROKEN]["flags"]
    assert any(
        f.startswith("Part (i) lost: tap test") and "tap.csv line 5" in f and "abc" in f
        for f in flags
    ), flags
    assert any(f.startswith("Part (iv) lost: PI control") and "pi.toml" in f for f in flags)
    assert any(f.startswith("file pid_scope.mat cannot be used (cannot read it") for f in flags)
    assert len(flags) == 3, flags  # no "missing part" or "unrecognised file" said twice
    assert row["B_eq_tap_fit [kg/s]"] == "" and row["pi_rms [m]"] == ""
    cart = carts[BROKEN]
    assert float(row["f_c_ramp_fit [N]"]) == pytest.approx(cart["f_c"], rel=0.02)
    assert float(row["B_eq_p50 [kg/s]"]) > 0  # Part (ii) ran (its f_c held: no tap's)
    assert row["pid_measured_settling_time [s]"] != "" and row["spec"] in ("pass", "fail")
    report = (out / "students" / BROKEN / "report.md").read_text()
    assert "Files that cannot be used (each costs only its part)" in report
    assert f"{BROKEN}: Part (i) lost" in stdout


def test_each_students_numbers_recover_its_own_cart(ran):
    """Against the generator's truth (an independent reference): B_eq from the tap within
    1 %, f_c from the ramp within 2 % (the built-in lab recovers both to 1e-4)."""
    _, out, carts, _, _, _ = ran
    rows = _rows(out)
    for name, cart in carts.items():
        if name == BROKEN:  # its tap is broken
            continue
        assert float(rows[name]["B_eq_tap_fit [kg/s]"]) == pytest.approx(cart["B_eq"], rel=0.01)
        if name != MISSING:
            assert float(rows[name]["f_c_ramp_fit [N]"]) == pytest.approx(cart["f_c"], rel=0.02)
    spread = [cart["B_eq"] for cart in carts.values()]
    assert max(spread) - min(spread) > 0.5  # different carts


def test_the_spec_verdict_follows_part_v(ran):
    _, out, _, _, _, _ = ran
    for name, row in _rows(out).items():
        if row["status"] != "complete":
            assert row["spec"] == "n/a"
            continue
        settling = float(row["pid_measured_settling_time [s]"])
        overshoot = float(row["pid_measured_overshoot [%]"])
        expected = "pass" if settling < 1.0 and overshoot < 5.0 else "fail"
        assert row["spec"] == expected, name


def test_the_page_is_self_contained_with_figures_and_links(ran):
    _, out, _, _, _, _ = ran
    page = (out / "class.html").read_text()
    assert page.count("data:image/png;base64,") == 2
    assert "http://" not in page and "https://" not in page
    assert 'href="students/student-01/report.html"' in page
    assert f'{EMPTY}</td><td class="bad">failed:' in page
    for name in ("distributions.png", "overlays.png"):
        assert (out / "figures" / name).stat().st_size > 10_000
    assert (out / "logs" / f"{EMPTY}.log").read_text().startswith("failed:")


# ---------------------------------------------------------------- outliers, without a lab


def _student(name, b_eq, *, missing=(), f_c_lower=None):
    s = Student(name, Path(name), status="complete")
    s.results = {
        "values": {
            "B_eq_tap_fit": {"value": b_eq, "unit": "kg/s", "label": "B_eq, fit", "part": "i"},
            "pid_kp": {"value": 250.0, "unit": "V/m", "label": "tuned kp", "part": "pre-lab"},
        },
        "data": {"missing": list(missing)},
    }
    if f_c_lower is not None:
        s.results["values"]["f_c_lower_p_step"] = {
            "value": f_c_lower,
            "unit": "N",
            "label": "f_c lower bound from the P-control steady state (p50.toml)",
            "part": "iii",
            "bound": "lower",
        }
    return s


def test_a_b_eq_ten_times_the_median_is_flagged_and_two_times_is_not():
    students = [_student(f"s{k}", b) for k, b in enumerate((4.0, 4.5, 5.0, 9.0, 50.0))]
    columns = classroom.columns_of(students)
    classroom.flag(students, columns)
    assert [bool(s.flags) for s in students] == [False, False, False, False, True]
    assert "10 x the class median 5 kg/s" in students[-1].flags[0]
    assert students[-1].marked == {"B_eq_tap_fit"}
    assert classroom.constant_columns(students, columns) == {"pid_kp": 250.0}
    low = Column("B_eq_tap_fit", "B_eq", "kg/s", "i")
    assert classroom.outlier(0.5, 5.0, low) is not None  # a tenth of it too
    assert classroom.outlier(0.51, 5.0, low) is None


def test_a_bound_is_no_estimate_and_is_not_judged_an_outlier():
    """A P-control run that stopped near its target bounds f_c from below by almost nothing
    (0.029 N for the class's highest true f_c): a bound far below the others' is no outlier."""
    lows = (0.28, 0.31, 0.25, 0.30, 0.029)
    students = [_student(f"s{k}", 4.5, f_c_lower=f) for k, f in enumerate(lows)]
    columns = classroom.columns_of(students)
    assert {c.key: c.bound for c in columns}["f_c_lower_p_step"] == "lower"
    classroom.flag(students, columns)
    assert not any(s.flags for s in students)
    assert "f_c_lower_p_step" not in classroom.class_medians(students, columns)


def test_the_lab_marks_its_f_c_bound_as_a_bound():
    """The lab's results.json says which numbers are bounds (tuning.lab.context.Value.bound):
    Part (iii)'s lower bound on f_c from a P-control run."""
    from types import SimpleNamespace

    from tuning.lab import part_iii

    bound = SimpleNamespace(error=None, name="p50.toml", slot="p_step", lower=0.029)
    model = SimpleNamespace(f_c=0.6, f_c_source="fit to the ramp")
    steady = SimpleNamespace(bound=0.01, e_sim=0.01, recording=None)
    part = SimpleNamespace(ramp=SimpleNamespace(recording=None), steady=steady, model=model)
    part.bounds = (bound,)
    found = {v.key: v.to_json() for v in part_iii.values(part)}
    assert found["f_c_lower_p_step"]["bound"] == "lower" and "bound" not in found["f_c"]


def test_too_few_students_for_a_median_flag_no_outlier():
    students = [_student("a", 4.0), _student("b", 400.0)]
    classroom.flag(students, classroom.columns_of(students))
    assert not any(s.flags for s in students)


def test_a_class_folder_without_sub_folders_is_one_clear_error(tmp_path):
    from jaxcart.errors import UserError

    (tmp_path / "tap.toml").write_text("kind = 'tap'\n")
    with pytest.raises(UserError, match="no sub-folders; put each student"):
        classroom.find_students(tmp_path)
    with pytest.raises(UserError, match="no such folder"):
        classroom.find_students(tmp_path / "nope")
    (tmp_path / "alice").mkdir()
    (tmp_path / "report").mkdir()
    (tmp_path / "report" / "class.csv").write_text("student\n")
    students, stray = classroom.find_students(tmp_path)
    assert [s.name for s in students] == ["alice"]
    assert stray == ["tap.toml", "report/ (a class report)"]


# ---------------------------------------------------------------- a worker that dies


def _crash_or_complete(folder, out, log, *, diagnosis=False):
    """A stand-in for the lab in the worker: the folder named "crasher" kills its process;
    each records when it ran in its log."""
    started = time.time()
    if Path(folder).name == "crasher":
        os._exit(3)
    time.sleep(0.2)
    Path(log).write_text(f"{started} {time.time()}\n")
    return {"status": "complete", "error": None, "seconds": 0.0, "runs": {}}


def test_the_lead_runs_alone_first_and_a_worker_that_dies_fails_only_its_student(tmp_path):
    """With the compilation cache on, the student with the most files (the one whose lab
    compiles the most) runs alone before the others start; a process that dies is its
    student's failure alone."""
    (tmp_path / "logs").mkdir()
    students = [Student(n, tmp_path / n) for n in ("alice", "bob", "crasher")]
    for student, files in zip(students, (1, 3, 1), strict=True):
        student.folder.mkdir()
        for k in range(files):
            (student.folder / f"run{k}.toml").write_text("")
    assert classroom.lead(students).name == "bob"
    said = []
    classroom.run_all(
        students,
        tmp_path,
        workers=2,
        diagnosis=False,
        cache=True,
        say=said.append,
        job=_crash_or_complete,
    )
    status = {s.name: s.status for s in students}
    assert status == {"alice": "complete", "bob": "complete", "crasher": "failed"}
    assert "process died" in students[2].error
    assert said[0] == "bob first, alone: its lab compiles the class's programs once"
    assert said[1].startswith("[1/3] bob: complete") and len(said) == 4
    bob_end = float((tmp_path / "logs" / "bob.log").read_text().split()[1])
    alice_start = float((tmp_path / "logs" / "alice.log").read_text().split()[0])
    assert bob_end <= alice_start


def test_the_files_the_lab_used_and_those_it_did_not(tmp_path):
    """used_files follows the lab's own reading of the folder: each experiment file, the data
    it maps and lab.toml are used; a stray file and a file the lab read but gave no part are
    not; a sub-folder is not a file."""
    import shutil

    from tuning.lab import data
    from tuning.lab.inputs import find_inputs

    for stem in ("tap", "p50"):
        for suffix in (".toml", ".csv"):
            shutil.copy(data.builtin_dir() / f"{stem}{suffix}", tmp_path / f"{stem}{suffix}")
    (tmp_path / "notes.txt").write_text("cart 7\n")
    (tmp_path / "old.toml").write_text('description = "no kind"\n')
    (tmp_path / "photos").mkdir()
    used = classroom.used_files(find_inputs(tmp_path))
    assert set(used) >= {"tap.toml", "tap.csv", "p50.toml", "p50.csv"}
    results = {"data": {"unused": [{"file": "old.toml", "reason": "not an experiment file"}]}}
    assert classroom.unrecognised_files(tmp_path, results, used) == [
        ("notes.txt", "not read by the lab"),
        ("old.toml", "not an experiment file"),
    ]
