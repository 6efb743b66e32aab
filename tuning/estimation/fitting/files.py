"""A fit's plant file: the fitted plant with a [fit] table of what the fit knows."""

from __future__ import annotations

from pathlib import Path

from jaxcart import plantspec
from jaxcart.params import Plant
from tuning.estimation.fitting.names import canonical
from tuning.estimation.fitting.result import FitResult


def fit_table(result: FitResult, sources=()) -> dict:
    """What a fit knows, for a plant file's [fit] table: the structure fitted, every fitted
    parameter's value and standard error, the parameters held or not identifiable (the value
    held at, why), the RMS before and after and the noise floor [m], whether the model explains
    the data and the optimizers converged, the warnings, the recordings."""
    doc = result.to_json()
    fitted = {n: e for n, e in result.params.items() if e.identifiable and e.value is not None}
    held = {n: e.note for n, e in result.params.items() if not e.identifiable}
    table = {
        "structure": list(result.plant().structure) or ["nominal"],
        "fitted": [canonical(n) for n in fitted],
        "value": {canonical(n): e.value for n, e in fitted.items()},
        "stderr": {canonical(n): e.stderr for n, e in fitted.items()},
        "held": [canonical(n) for n in held],
        "held_at": {
            canonical(n): e.held_at
            for n, e in result.params.items()
            if not e.identifiable and e.held_at is not None
        },
        "why_held": {canonical(n): note or "" for n, note in held.items()},
        "rms_before": doc["rms_before"],
        "rms_after": doc["rms_after"],
        "noise_floor": result.noise_floor,
        "model_explains_data": not result.misfit,
        "converged": result.converged,
        "warnings": result.warnings,
        "recordings": [str(x) for x in sources],
    }
    return {k: v for k, v in table.items() if v is not None}


def write_fitted_plant(path, result: FitResult, *, sources=(), force: bool = False) -> Path:
    """Write the fitted plant as a plant file (TOML, :mod:`jaxcart.plantspec`) with a [fit]
    table (:func:`fit_table`); refuses to overwrite unless ``force``."""
    return plantspec.write_plant_file(
        path, result.plant(), fit=fit_table(result, sources), force=force
    )


def load_fitted_plant(path) -> Plant:
    """The plant of a plant file (written by ``jaxcart fit --out`` or ``diagnose``)."""
    return plantspec.read_plant_file(path)[0]
