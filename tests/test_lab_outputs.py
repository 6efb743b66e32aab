"""`jaxcart lab` with bad inputs and interrupted runs: every input checked before anything is
computed (one line, no traceback), and the report written atomically (a staging folder renamed
when complete), so an interrupted run leaves nothing that blocks a plain rerun.

The report's sections are replaced by a stub where only the writing is under test (the whole
report is tested in tests/test_lab.py).
"""

import os
import shutil
import subprocess
import sys

import pytest

from jaxcart.errors import UserError
from tuning.lab import data, inputs, report
from tuning.lab.report import run_lab


def _copy(folder, names=("tap",)):
    folder.mkdir(parents=True, exist_ok=True)
    for stem in names:
        for suffix in (".toml", ".csv"):
            shutil.copy(data.builtin_dir() / f"{stem}{suffix}", folder / f"{stem}{suffix}")
    return folder


def _stub_sections(lab, folder, builtin, plant, diagnosis, executor):
    lab.doc.paragraph("stub report")
    report._write(lab)


def _one_error_line(capsys, argv):
    from tuning.commands.main import main

    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if not line.startswith("lab [")]
    assert len(lines) == 1 and lines[0].startswith("jaxcart lab: error:"), captured.err
    assert "Traceback" not in captured.err
    return lines[0]


def test_a_folder_named_like_an_experiment_file(tmp_path, capsys):
    folder = _copy(tmp_path / "d")
    (folder / "exp.toml").mkdir()
    found = inputs.find_inputs(folder)
    assert ("exp.toml", "a folder, not an experiment file") in found.unused
    assert set(found.recordings) == {"tap"}
    (folder / "lab.toml").write_text('[recordings]\ntap = "exp.toml"\n')
    line = _one_error_line(capsys, ["lab", "--data", str(folder), "--out", str(tmp_path / "o")])
    assert "exp.toml" in line and "folder" in line
    assert not (tmp_path / "o").exists()


def test_a_tap_in_mm_is_refused_before_any_computation(tmp_path, capsys):
    folder = _copy(tmp_path / "d")
    lines = (folder / "tap.csv").read_text().splitlines()
    rows = [f"{t},{float(y) * 1e3:.5f}" for t, y in (r.split(",") for r in lines[1:])]
    (folder / "tap.csv").write_text("\n".join([lines[0], *rows]) + "\n")
    line = _one_error_line(capsys, ["lab", "--data", str(folder), "--out", str(tmp_path / "o")])
    assert "tap" in line and "mm" in line
    assert not (tmp_path / "o").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_an_interrupted_lab_leaves_nothing_behind(tmp_path, monkeypatch):
    out = tmp_path / "report"

    def interrupted(lab, *args):
        (lab.out / "figures" / "half.png").write_bytes(b"")
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "_sections", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_lab(None, out)
    assert sorted(tmp_path.iterdir()) == []  # neither the report nor its staging folder
    # A plain rerun (no --force) writes the report.
    monkeypatch.setattr(report, "_sections", _stub_sections)
    assert run_lab(None, out) == out
    assert "stub report" in (out / "report.md").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_a_killed_run_s_staging_folder_is_cleared(tmp_path, monkeypatch):
    done = subprocess.Popen([sys.executable, "-c", "pass"])
    done.wait()  # a process id that has ended
    stale = tmp_path / f".report.partial-{done.pid}"
    (stale / "figures").mkdir(parents=True)
    live = tmp_path / f".report.partial-{os.getppid()}"  # a live process's: left alone
    live.mkdir()
    monkeypatch.setattr(report, "_sections", _stub_sections)
    run_lab(None, tmp_path / "report")
    assert not stale.exists() and live.exists()
    assert (tmp_path / "report" / "report.md").is_file()


def test_force_replaces_the_report_and_keeps_other_files(tmp_path, monkeypatch):
    out = tmp_path / "report"
    (out / "figures").mkdir(parents=True)
    (out / "report.md").write_text("old")
    (out / "figures" / "old.png").write_bytes(b"")
    (out / "notes.txt").write_text("mine")
    monkeypatch.setattr(report, "_sections", _stub_sections)
    with pytest.raises(UserError, match="--force"):
        run_lab(None, out)
    assert (out / "report.md").read_text() == "old"
    run_lab(None, out, force=True)
    assert "stub report" in (out / "report.md").read_text()
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "figures" / "old.png").exists()  # figures/ is the report's own
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_an_output_under_a_file_is_refused_before_computing(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    called = []
    monkeypatch.setattr(report, "_sections", lambda *a: called.append(1))
    with pytest.raises(UserError, match="cannot create"):
        run_lab(None, tmp_path / "file" / "report")
    assert not called
