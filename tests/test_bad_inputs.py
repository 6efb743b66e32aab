"""The catalogue of bad input files (tests/bad_inputs, answers.toml) through the commands,
and the commands' outputs on a full disk or a read-only file system.

Every case: the command's main() in-process, the one-line answer the catalogue names (or exit
0 where the input is valid), never a traceback, no output left behind (not even a hidden
temporary file), and every input file byte for byte and time stamp as it was. The lab and
diagnose run only where the answer comes before any fitting (they are expensive).
"""

from __future__ import annotations

import errno
import hashlib
import io
import re
import shutil
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest

import hw.atomicio
from hw.atomicio import OutputError, atomic_paths, write_text
from tuning.commands.main import main

CATALOGUE = Path(__file__).parent / "bad_inputs"
ANSWERS = tomllib.loads((CATALOGUE / "answers.toml").read_text(encoding="utf-8"))
COMMANDS = ("simulate", "fit", "diagnose", "lab")
#: Every rendering of the same closed-loop step, for the cases built here.
BASE = CATALOGUE / "toml_with_bom"


def _base_toml(data: str) -> str:
    text = (BASE / "run.toml").read_text(encoding="utf-8-sig")
    return text.replace('data = "run.csv"', f'data = "{data}"')


def _base_csv() -> str:
    return (BASE / "run.csv").read_text(encoding="utf-8")


def _xlsx() -> bytes:
    """A minimal workbook: what Excel saves (a zip with its content types)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("[Content_Types].xml", '<?xml version="1.0"?><Types/>')
        zf.writestr("xl/workbook.xml", "<workbook/>")
    return buf.getvalue()


def _utf16_answer(name):
    return f"{name} is saved as UTF-16 \\(Unicode text\\), not UTF-8; save it as UTF-8 text"


#: Cases whose files are binary or folders, built in the test: {name: (files, args, answers)}.
#: A file's content is bytes, text (UTF-8) or None for an empty folder.
BINARY_CASES = {
    "utf16_toml_with_bom": (
        lambda: {"run.toml": _base_toml("run.csv").encode("utf-16"), "run.csv": _base_csv()},
        ["run.toml"],
        {"all": _utf16_answer("run\\.toml")},
    ),
    "utf16_toml_without_bom": (
        lambda: {"run.toml": _base_toml("run.csv").encode("utf-16-le"), "run.csv": _base_csv()},
        ["run.toml"],
        {"all": _utf16_answer("run\\.toml")},
    ),
    "utf16_csv": (
        lambda: {"run.toml": _base_toml("run.csv"), "run.csv": _base_csv().encode("utf-16")},
        ["run.toml"],
        {"all": _utf16_answer("run\\.csv")},
    ),
    "utf16_txt_without_bom": (
        lambda: {"run.toml": _base_toml("run.txt"), "run.txt": _base_csv().encode("utf-16-le")},
        ["run.toml"],
        {"all": _utf16_answer("run\\.txt")},
    ),
    "xlsx_as_data": (
        lambda: {"run.toml": _base_toml("run.xlsx"), "run.xlsx": _xlsx()},
        ["run.toml"],
        {"all": "run\\.xlsx is an Excel workbook \\(\\.xlsx\\).*Save As > CSV UTF-8"},
    ),
    "xlsx_given_as_experiment": (
        lambda: {"run.xlsx": _xlsx()},
        ["run.xlsx"],
        {
            c: "run\\.xlsx is an Excel workbook.*an experiment is a \\.toml file"
            for c in ("simulate", "fit", "diagnose")
        },
    ),
    "binary_data": (
        lambda: {"run.toml": _base_toml("run.csv"), "run.csv": bytes(range(256)) * 4},
        ["run.toml"],
        {"all": "run\\.csv is a binary file, not text; give a CSV file"},
    ),
    "data_is_a_folder": (
        lambda: {"run.toml": _base_toml("run.csv"), "run.csv/": None},
        ["run.toml"],
        {"all": "data file run\\.csv is a folder \\(.*\\); give the path of the data file inside"},
    ),
    "experiment_is_a_folder": (
        lambda: {"run.toml/": None},
        ["run.toml"],
        {c: "run\\.toml is a folder; give the path of a \\.toml file" for c in ("simulate", "fit")},
    ),
}


def _cases():
    out = []
    for name, spec in ANSWERS.items():
        for command in COMMANDS:
            if command in spec or ("all" in spec and command not in spec):
                out.append(pytest.param(name, command, id=f"{name}-{command}"))
    for name, (_, _, answers) in BINARY_CASES.items():
        for command in COMMANDS:
            if command in answers or "all" in answers:
                out.append(pytest.param(name, command, id=f"{name}-{command}"))
    return out


def _answer(name, command) -> tuple[list[str], str]:
    if name in ANSWERS:
        spec = ANSWERS[name]
        return spec.get("args", ["run.toml"]), spec.get(command, spec.get("all"))
    _, args, answers = BINARY_CASES[name]
    return args, answers.get(command, answers.get("all"))


def _make_case(name, folder: Path) -> None:
    if name in ANSWERS:
        shutil.copytree(CATALOGUE / name, folder, dirs_exist_ok=True)
        return
    files = BINARY_CASES[name][0]()
    for rel, content in files.items():
        path = folder / rel.rstrip("/")
        if content is None:
            path.mkdir(parents=True)
            (path / "inside.csv").write_text(_base_csv())
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content, encoding="utf-8", newline="")


def _snapshot(folder: Path) -> dict:
    """{relative path: (sha256, mtime_ns)} of every file (hidden ones too) under ``folder``."""
    return {
        str(p.relative_to(folder)): (
            hashlib.sha256(p.read_bytes()).hexdigest(),
            p.stat().st_mtime_ns,
        )
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _argv(command, args, case: Path, out: Path) -> list[str]:
    files = [str(case / a) for a in args]
    if command == "simulate":
        return ["simulate", files[0], "--horizon", "0.1", "--out", str(out / "sim.csv")]
    if command == "fit":
        return [
            "fit",
            *files,
            "--quiet",
            "--json",
            str(out / "fit.json"),
            "--out",
            str(out / "plant.toml"),
        ]
    if command == "diagnose":
        return ["diagnose", *files, "--quiet", "--out", str(out / "diagnose")]
    return ["lab", "--data", str(case), "--out", str(out / "lab"), "--no-diagnosis"]


def _run(argv, capsys) -> tuple[int, str, str]:
    capsys.readouterr()
    try:
        status = main(argv)
    except SystemExit as exc:
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


@pytest.mark.parametrize(("name", "command"), _cases())
def test_each_bad_input_gets_its_one_line_answer(name, command, tmp_path, capsys):
    case, out = tmp_path / "case", tmp_path / "out"
    case.mkdir()
    _make_case(name, case)
    before = _snapshot(case)
    args, answer = _answer(name, command)
    status, stdout, stderr = _run(_argv(command, args, case, out), capsys)
    assert "Traceback" not in stdout + stderr
    assert _snapshot(case) == before, "an input file was changed"
    if answer.startswith(("ok", "exit ")):
        expected = 0 if answer.startswith("ok") else int(answer.split()[1].rstrip(":"))
        assert status == expected, stderr
        says = answer.partition(":")[2].strip()
        assert not says or re.search(says, stdout + stderr), stdout + stderr
        if command == "simulate":
            assert _files(out) == ["sim.csv", "sim.toml"]
        return
    errors = [line for line in stderr.splitlines() if ": error: " in line]
    assert status == 2, stderr
    assert len(errors) == 1, stderr
    line = errors[0]
    assert line.startswith(f"jaxcart {command}: error: "), line
    assert line.isprintable(), repr(line)
    assert re.search(answer, line), line
    assert not out.exists(), f"output left behind: {_files(out) or 'an empty folder'}"


def test_the_catalogue_has_a_folder_for_each_answer_and_an_answer_for_each_folder():
    folders = {p.name for p in CATALOGUE.iterdir() if p.is_dir()}
    assert folders == set(ANSWERS)
    assert not folders & set(BINARY_CASES)
    for name, spec in ANSWERS.items():
        assert set(spec) <= {"args", "all", *COMMANDS}, name
        for key in set(spec) - {"args"}:
            if not spec[key].startswith(("ok", "exit ")):
                re.compile(spec[key])


# ---------------------------------------------------------------- outputs that cannot be written


class _FullDisk:
    """A file object that takes ``room`` bytes and then fails as a full disk does."""

    def __init__(self, f, room, code):
        self.f, self.room, self.code = f, room, code

    def write(self, data):
        size = len(data)
        if size > self.room:
            raise OSError(self.code, "simulated", None)
        self.room -= size
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def _fail_writes(monkeypatch, *, suffix=None, room=100, code=errno.ENOSPC):
    """Every output opened through hw.atomicio (those whose name ends in ``suffix``, or all)
    fails after ``room`` bytes with ``code``."""
    real = open

    def opener(path, mode="r", **kwargs):
        f = real(path, mode, **kwargs)
        if suffix is None or str(path).endswith(suffix):
            return _FullDisk(f, room, code)
        return f

    monkeypatch.setattr(hw.atomicio, "_open", opener)


@pytest.mark.parametrize(
    ("suffix", "code", "says"),
    [
        (".csv", errno.ENOSPC, "the disk is full"),
        (".toml", errno.ENOSPC, "the disk is full"),
        (".png", errno.ENOSPC, "the disk is full"),
        (None, errno.EROFS, "the file system is read-only"),
    ],
)
def test_simulate_on_a_full_or_read_only_disk_leaves_nothing_and_the_rerun_works(
    suffix, code, says, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    argv = ["simulate", "--horizon", "0.1", "--out", "out/run.csv", "--plot", "out/run.png"]
    with monkeypatch.context() as m:
        _fail_writes(m, suffix=suffix, code=code)
        status, _, stderr = _run(argv, capsys)
    assert status == 2 and "Traceback" not in stderr
    (line,) = stderr.splitlines()
    assert re.match(f"jaxcart simulate: error: cannot write .*: {says}; ", line), line
    assert not (tmp_path / "out").exists()  # not even the folder it made
    assert _run(argv, capsys)[0] == 0  # nothing left that blocks the rerun
    assert _files(tmp_path / "out") == ["run.csv", "run.png", "run.toml"]


def test_diagnose_on_a_full_disk_leaves_no_report(tmp_path, monkeypatch, capsys):
    case = tmp_path / "case"
    shutil.copytree(CATALOGUE / "amplifier_off", case)
    argv = ["diagnose", str(case / "run.toml"), "--quiet", "--out", str(tmp_path / "d")]
    with monkeypatch.context() as m:
        _fail_writes(m, room=10)
        status, _, stderr = _run(argv, capsys)
    errors = [line for line in stderr.splitlines() if "error" in line]
    assert status == 2 and len(errors) == 1 and "the disk is full" in errors[0], stderr
    assert not (tmp_path / "d").exists()
    assert _run(argv, capsys)[0] == 1 and _files(tmp_path / "d") == ["report.md"]  # not diagnosed


def test_fit_outputs_are_all_written_or_none(tmp_path, monkeypatch, capsys):
    case = tmp_path / "case"
    shutil.copytree(CATALOGUE / "toml_with_bom", case)
    out = tmp_path / "out"
    argv = ["fit", str(case / "run.toml"), "--params", "B_eq", "--quiet"]
    argv += ["--json", str(out / "fit.json"), "--out", str(out / "plant.toml")]
    argv += ["--plot", str(out / "fit.png")]
    with monkeypatch.context() as m:
        _fail_writes(m, suffix=".png")  # the last of the three
        status, _, stderr = _run(argv, capsys)
    assert status == 2 and "Traceback" not in stderr, stderr
    assert re.search(r"fit: error: cannot write .*fit\.png: the disk is full", stderr), stderr
    assert not out.exists()


def test_the_lab_report_folder_is_never_left_half_written(tmp_path, monkeypatch):
    from jaxcart.errors import UserError
    from tuning.lab.report import staged

    final = tmp_path / "reports" / "lab"  # its folder made, then removed with it
    with monkeypatch.context() as m:
        _fail_writes(m)
        with pytest.raises(UserError, match=f"cannot write {final}/report.md: the disk is full"):
            with staged(final) as tmp:
                write_text(tmp / "report.md", "x" * 1000, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_grid_and_tune_outputs_and_gains_files_are_atomic(tmp_path, monkeypatch):
    from hw.control_law import PID
    from hw.gains import GainsFileError, write_gains
    from hw.jsonio import write_json
    from tuning.design.grid import _open

    with monkeypatch.context() as m:
        _fail_writes(m)
        with pytest.raises(OutputError, match="grid.npz: the disk is full"):
            with _open(tmp_path / "grid.npz", False) as f:
                f.write(b"x" * 1000)
        with pytest.raises(OutputError, match="tune.json: the disk is full"):
            write_json(tmp_path / "tune.json", {"kp": np.arange(100)})
        with pytest.raises(GainsFileError, match="gains.json: the disk is full"):
            write_gains(tmp_path / "gains.json", PID(kp=50.0))
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "grid.npz").write_bytes(b"mine")
    with pytest.raises(OutputError, match="grid.npz exists; choose another name or pass --force"):
        with _open(tmp_path / "grid.npz", False) as f:
            f.write(b"theirs")
    assert (tmp_path / "grid.npz").read_bytes() == b"mine"


def test_files_written_together_are_renamed_together(tmp_path, monkeypatch):
    a, b = tmp_path / "run.csv", tmp_path / "run.toml"
    with pytest.raises(OutputError, match="run.toml: the file system is read-only"):
        with atomic_paths(a, b) as (ta, tb):
            ta.write_text("t,y\n")
            tb.write_text("kind = 'tap'\n")
            real = hw.atomicio.os.link

            def link(src, dst):
                if str(dst).endswith(".toml"):
                    raise OSError(errno.EROFS, "simulated")
                return real(src, dst)

            monkeypatch.setattr(hw.atomicio.os, "link", link)
            monkeypatch.setattr(hw.atomicio.os, "replace", link)
    assert list(tmp_path.iterdir()) == []  # the CSV, renamed first, is taken back
