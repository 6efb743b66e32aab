"""Each driven run's own drive limits (a structure with the limits free per run): whether a
run's limit acts (below what that run drove), whether the runs' limits are one drive's spread,
each recording's own values, and the cart's plant at the median of the limits that act. Whether
they differ between runs at all is a significance test (:mod:`.significance`).
"""

from __future__ import annotations

import math

import numpy as np

from jaxcart.effects import REGISTRY
from tuning.estimation.diagnose.candidate_runs import exact_plants
from tuning.estimation.diagnose.policy import RUN_SPREAD
from tuning.estimation.diagnose.scoring import rms
from tuning.estimation.diagnose.structures import (
    PER_RUN,
    effect_params,
    limit_params,
    per_run_params,
    structure,
)
from tuning.estimation.engine import parameters


def _limits_by_run(values, peaks):
    """For each drive limit free per run in ``values``: (name, the signal it limits, {run: own
    value}, {run: what the run demonstrably drew: its own value where it acts, else its
    largest command or current (``peaks``)}, {run: own value where it acts})."""
    for n in limit_params():
        signal = next(REGISTRY[e].limits for e in effect_params() if n in effect_params()[e])
        own = {
            parameters.recording_of(k): v
            for k, v in values.items()
            if "@" in k and parameters.base_name(k) == n
        }
        peak = {i: peaks.get(f"{signal}@{i}", math.inf) for i in own}
        acting = {i: v for i, v in own.items() if v < peak[i]}
        shown = {i: min(v, peak[i]) for i, v in own.items()}
        yield n, signal, own, shown, acting


def per_run_inconsistency(values, peaks) -> str:
    """Why the drive limits free per run are more than one drive's spread ("" when they are
    not): a run's own limit below what another run of the same drive demonstrably drew (its own
    limit where it acts, else its largest command or current) by more than :data:`RUN_SPREAD`.
    Such a structure does not seed the forward selection, and where it is named for its
    held-out prediction the verdict says so."""
    for n, signal, own, shown, acting in _limits_by_run(values, peaks):
        if len(own) < 2 or not acting:
            continue
        low = min(acting, key=acting.get)
        high = max(shown, key=shown.get)
        if shown[high] > RUN_SPREAD * acting[low]:
            unit, ratio = parameters.spec(n).unit, shown[high] / acting[low]
            return (
                f"run {low + 1}'s {n} is {ratio:.2g} times below what run {high + 1} drove "
                f"({signal} {shown[high]:.3g} {unit}): "
                f"more than one drive varies from run to run (at most {RUN_SPREAD:g} times): "
                f"run {low + 1} may show something the library does not model"
            )
    return ""


def drive_runs(values, peaks) -> set:
    """The runs' own drive values (``v_sat@2``, ``gamma_scale@3``: keys of ``values``) that say
    what the drive does from run to run, so that the cart's value is their median and a next
    run's is drawn like them: every gain; of the limits, those that act (:func:`acts`), less
    any more than :data:`RUN_SPREAD` below what another run drove
    (:func:`per_run_inconsistency`: that run shows something else, e.g. its drive gain as a
    clipped peak) where two or more acting runs lie within it (the drive's spread measured
    without it; one acting run alone is all there is, and is kept)."""
    gains = set(per_run_params()) - set(limit_params())
    out = {k for k in values if "@" in k and parameters.base_name(k) in gains}
    for n, _, _, shown, acting in _limits_by_run(values, peaks):
        within = {i for i, v in acting.items() if RUN_SPREAD * v >= max(shown.values())}
        out |= {f"{n}@{i}" for i in (within if len(within) >= 2 else acting)}
    return out


def acts(name, key, value, peaks) -> bool:
    """Whether drive limit ``name``'s value in run ``key`` (``i_max@2``) is below what that run
    drove (``peaks``' ``{command,current}@i``), so that it acts (any other value: True)."""
    signal = next((REGISTRY[e].limits for e in effect_params() if name in effect_params()[e]), "")
    return not signal or value < peaks.get(f"{signal}@{parameters.recording_of(key)}", math.inf)


def cart_plant(best, base_plants, segments, peaks):
    """The cart's plant of ``best`` (the first driven run's); a drive limit free per run at
    the median of the runs' values that say what the drive does (:func:`drive_runs`: above
    what a run drove, its value is not determined), each run's own in the per-recording
    results."""
    # no run's own copy: exact_plants would give the first driven run its own, not the median
    values = {
        k: v
        for k, v in best.values.items()
        if "@" not in k or parameters.base_name(k) not in per_run_params()
    }
    drive = drive_runs(best.values, peaks)
    for n in per_run_params():
        own = {k: v for k, v in best.values.items() if "@" in k and parameters.base_name(k) == n}
        acting = [v for k, v in own.items() if k in drive]
        if own:
            values[n] = float(np.median(acting or list(own.values())))
    cand = structure(tuple(p for p in best.parts if p != PER_RUN))
    plants = exact_plants(cand, base_plants, values)
    motor = [p for p, s in zip(plants, segments, strict=True) if s.motor]
    return motor[0] if motor else plants[0]


def per_recording(best, names, segments, base, cov, peaks) -> dict:
    """{recording name: {"parameters": its own values ("acts": False for a limit above what
    that run drove: {command,current}@i of ``peaks``), "rms_before", "rms_after" [m]}}."""
    out = {}
    for i, (name, seg) in enumerate(zip(names, segments, strict=True)):
        own = {}
        for k in best.free:
            if k.endswith(f"@{i}") and parameters.base_name(k) not in parameters.NUISANCE:
                n = parameters.base_name(k)
                own[n] = {
                    "value": best.values[k],
                    "stderr": cov.stderr({k: 1.0}),
                    "unit": parameters.spec(n).unit,
                    "acts": acts(n, k, best.values[k], peaks),
                }
        if names.count(name) > 1:  # recordings of one name told apart by their place
            name = f"{name} #{i + 1}"
        out[name] = {
            "kind": seg.kind,
            "parameters": own,
            "rms_before": rms([base.residuals[i]]),
            "rms_after": rms([best.residuals[i]]),
        }
    return out
