"""A fit of a very long recording says what it will cost before it starts."""

from pathlib import Path

import pytest

import tuning.estimation.fit
from tuning.commands import fit as fit_command
from tuning.commands.main import main

TAP = str(Path(__file__).parent.parent / "jaxcart" / "data" / "tap.toml")


def test_long_fit_warns_before_fitting(monkeypatch, capsys):
    class Started(Exception):
        pass

    def started(*args, **kwargs):
        raise Started

    monkeypatch.setattr(tuning.estimation.fit, "fit", started)
    monkeypatch.setattr(fit_command, "LONG_FIT_SAMPLES", 1000)  # the tap has 2,500 samples
    with pytest.raises(Started):
        main(["fit", TAP, "--quiet"])
    err = capsys.readouterr().err
    assert "2,501 samples" in err or "2,500 samples" in err, err
    assert "crop the recording" in err
    monkeypatch.setattr(fit_command, "LONG_FIT_SAMPLES", 10**9)
    with pytest.raises(Started):
        main(["fit", TAP, "--quiet"])
    assert "samples" not in capsys.readouterr().err
