"""Recordings of the independent generator as experiment files (TOML + CSV,
docs/experiment-files.md), written by the project's own writer (``hw.expfile``) so that
``jaxcart.files.read_experiment`` reads them as it reads a user's file. The truth, the
artefacts and the seed go to the file's free-form ``[notes]`` table, which nothing fits from.

>>> import tempfile, pathlib
>>> from jaxcart.files import read_experiment
>>> from tuning.verification import experiments as ex
>>> folder = pathlib.Path(tempfile.mkdtemp())
>>> rec = make_recording(TrueCart(B_eq=1.5, f_c=0.4), ex.tap(horizon=1.0), folder / "tap.toml")
>>> read_experiment(rec.path).kind, rec.run.truth.motor_connected
('tap', False)
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import NamedTuple

import numpy as np

from hw.expfile import write_experiment_file
from tuning.verification.artefacts import REALISTIC, Artefacts
from tuning.verification.experiments import Experiment
from tuning.verification.independent_sim import Run, simulate
from tuning.verification.physics import SUBSTEPS
from tuning.verification.truth import TrueCart

#: The [notes] entry that names the generator.
GENERATOR = "tuning.verification (independent of jaxcart's simulators)"


class Recording(NamedTuple):
    """A written recording: its TOML path and the run it holds."""

    path: Path
    run: Run


def write_run(run: Run, toml_path, *, force: bool = False, drop: tuple = ()) -> Path:
    """Write ``run`` as ``name.toml`` + ``name.csv``: columns t [s], y [m] (what the encoder
    read), v [V] (the command sent; open and closed loop), r and e [m] (closed loop), less any
    in ``drop``; [controller] the PID that ran. Refuses to overwrite unless ``force``."""
    if run.diverged:
        raise ValueError(f"{toml_path}: the run diverged; nothing written")
    kind = run.kind
    columns = {"t": run.time, "y": run.position}
    if kind != "tap":
        columns["v"] = run.command
    if kind == "closed_loop":
        columns["r"] = run.reference
        columns["e"] = run.reference - run.position
    columns = {k: np.asarray(v, dtype=float) for k, v in columns.items() if k not in drop}
    return write_experiment_file(
        toml_path,
        columns,
        kind=kind,
        sample_time=run.experiment.sample_time,
        controller=run.experiment.pid,
        description=f"independent generator: {run.experiment.label}",
        tables={"notes": notes(run)},
        force=force,
    )


def notes(run: Run) -> dict:
    """The [notes] of a run's file: the generator, seed, truth (``truth_<name>``), artefacts
    (``artefact_<name>``) and a tap's push."""
    out = {"generator": GENERATOR, "seed": str(run.seed)}
    for name, value in run.truth.values().items():
        out[f"truth_{name}"] = _note(value)
    for name, value in asdict(run.artefacts).items():
        out[f"artefact_{name}"] = _note(value)
    if run.push is not None:
        shape, length, peak = run.push
        out.update(push_shape=shape, push_length=length, push_peak=peak)
    return out


def _note(value):
    if isinstance(value, bool | str):
        return value
    if isinstance(value, tuple | list):
        return ", ".join(repr(float(x)) for x in value)
    value = float(value)
    return value if not math.isnan(value) else "nan"


def make_recording(
    cart: TrueCart,
    experiment: Experiment,
    toml_path,
    artefacts: Artefacts = REALISTIC,
    *,
    seed=0,
    force: bool = False,
    drop: tuple = (),
    substeps: int = SUBSTEPS,
) -> Recording:
    """Make one recording: run ``experiment`` on ``cart`` with ``artefacts`` (default: what a
    real recording carries) and the draws of ``seed``, and write it as an experiment file at
    ``toml_path`` (:func:`write_run`)."""
    run = simulate(cart, experiment, artefacts, seed=seed, substeps=substeps)
    return Recording(write_run(run, toml_path, force=force, drop=drop), run)
