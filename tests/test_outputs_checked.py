"""Commands that compute for seconds or minutes refuse an unwritable output first, in one line."""

from pathlib import Path

import pytest

from tuning.commands.main import main

TAP = str(Path(__file__).parent.parent / "jaxcart" / "data" / "tap.toml")


@pytest.mark.parametrize(
    "argv",
    [
        ["grid", "--kp", "10:20:2", "--kd", "1:2:2", "--ki", "0:0:1", "--out", "{f}/g.npz"],
        ["grid", "--kp", "10:20:2", "--kd", "1:2:2", "--ki", "0:0:1", "--json", "{f}/g.json"],
        ["diagnose", TAP, "--out", "{f}/diag"],
        ["diagnose", TAP, "--out", "{d}/diag", "--json", "{f}/d.json"],
    ],
)
def test_output_under_a_file_fails_before_computing(tmp_path, capsys, monkeypatch, argv):
    import tuning.design.grid
    import tuning.estimation.diagnose

    def refuse(*args, **kwargs):
        raise AssertionError("computed before checking the outputs")

    for module, name in (
        (tuning.design.grid, "grid_search"),
        (tuning.design.grid, "evaluate_list"),
    ):
        monkeypatch.setattr(module, name, refuse)
    monkeypatch.setattr(tuning.estimation.diagnose, "diagnose", refuse)
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    argv = [a.format(f=blocker, d=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a file" in err[0], err
    assert "Traceback" not in err[0]
    assert not (tmp_path / "diag").exists()
