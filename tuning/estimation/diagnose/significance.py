"""Which parts of a structure are named: each effect's strength against its standard error (a
Wald test, :func:`significance`; the drive limits free per run: do they differ between runs),
values at a bound or outside what a cart of this lab has (:func:`implausible`), and the tie of
M with gamma_scale (:func:`swap_tie`). Each run's own limits are in :mod:`.per_run`; the
structures themselves in :mod:`.structures`, their exact runs in :mod:`.candidate_runs`, their
scores in :mod:`.scoring`.
"""

from __future__ import annotations

import math

from jaxcart import plantspec
from jaxcart.effects import REGISTRY
from jaxcart.params import TRACK_LENGTH
from tuning.estimation.diagnose.candidate_runs import exact_residuals, plant_of
from tuning.estimation.diagnose.per_run import acts
from tuning.estimation.diagnose.policy import (
    AT_BOUND,
    CORRECTION_MARGIN,
    SIGNIFICANCE,
    TIE,
)
from tuning.estimation.diagnose.scoring import rms, score
from tuning.estimation.diagnose.structures import (
    PARAM_ERRORS,
    PER_RUN,
    effect_params,
    per_run_params,
    structure,
    swapped_correction,
)
from tuning.estimation.engine import parameters


def at_bound(name: str, value: float) -> str:
    """Which bound ("lower", "upper") ``value`` sits at, of :data:`~batch.BOUNDS` (within
    :data:`AT_BOUND`: relative for a parameter fitted as a logarithm, else a tenth of it as a
    share of the range); "" for none."""
    if (
        parameters.base_name(name) not in parameters.superset()
        and parameters.base_name(name) not in parameters.NUISANCE
    ):
        return ""
    lo, hi = parameters.bounds(name)
    if parameters.is_log(name):
        if value <= lo * math.exp(AT_BOUND):
            return "lower"
        if value >= hi * math.exp(-AT_BOUND):
            return "upper"
        return ""
    tol = 0.1 * AT_BOUND * (hi - lo)
    if value <= lo + tol:
        return "lower"
    if value >= hi - tol:
        return "upper"
    return ""


def _strengths(part, values, peaks, start):
    """Each item a part names: (item, its strength, the strength's weights for its standard
    error, what the strength measures, where the item does nothing). The strength is the
    distance from the values where the item does nothing, positive when it acts: each effect
    declares its own (``Effect.strengths``); a correction is its distance from the start
    plant's value beyond :data:`CORRECTION_MARGIN`."""
    if part in effect_params():
        for effect in parameters.named_by(part):
            yield from REGISTRY[effect].strengths(values, peaks)
    for name in PARAM_ERRORS.get(part, ()):
        was = start[name]
        yield (
            name,
            abs(values[name] - was) - CORRECTION_MARGIN * abs(was),
            {name: math.copysign(1.0, values[name] - was)},
            f"{name} = {values[name]:.4g}",
            f"{CORRECTION_MARGIN:.0%} of the start plant's {was:.4g}",
        )


def significance(parts, values, stderr, peaks=None, start=None) -> dict:
    """Is each effect (and parameter correction) of a structure there? A Wald test.

    parts: the structure's parts (:attr:`~.structures.Candidate.parts`); values: its fitted values;
    stderr: ``f(weights) -> standard error`` of a linear combination of parameters
    (:meth:`~.engine.covariance.Covariance.stderr`); peaks: {"command": largest |command|
    sent [V], "current": largest |armature current| [A]} of the structure's own run
    (saturation, current limit);
    start: the start plant's M and gamma_scale.

    Each item's strength is its distance from the values where it does nothing: f_c from 0
    (Coulomb), f_s - f_c from 0 (stiction: static above kinetic), delay, deadzone and k_s from
    0, v_sat and i_max below the largest command and current of the run (a limit above them
    never acts), M and gamma_scale beyond :data:`CORRECTION_MARGIN` of the start plant's.
    z = strength / standard error; an item is significant when z > :data:`SIGNIFICANCE` and
    none of its part's parameters sits at a bound (:func:`at_bound`: the fit wanted a value
    beyond the range, its standard error means nothing). Returns {item: {"z", "why", "idle",
    "part"}} ("why" empty when significant; "idle": the item is where it does nothing, or
    under its least size worth naming: a value that changes the model by nothing one would
    name, :meth:`~.search.Search.choose`)."""
    peaks = peaks or {}
    start = start or {"M": 0.94, "gamma_scale": 1.0}
    out = {}
    for part in parts:
        if part == PER_RUN:
            out[PER_RUN] = _per_run_significance(values, stderr, peaks=peaks)
            continue
        params = effect_params().get(part) or PARAM_ERRORS.get(part, ())
        views = []
        for vals, pk, run in _views(params, values, peaks):
            bound = _bound_text(params, vals, per_run=run is not None)
            idle_part = bool(bound) and _own_at_neutral(part, vals)
            for item, strength, weights, what, neutral in _strengths(part, vals, pk, start):
                if run is not None:
                    weights = {_own(n, run, values): w for n, w in weights.items()}
                    what = f"{what} in run {run + 1}"
                z, why, idle = _judge(item, strength, weights, stderr, what, neutral, bound)
                views.append((item, z, why, idle or idle_part))
        for item in dict.fromkeys(v[0] for v in views):
            # Of a part free per run, the run where it is clearest.
            mine = [v for v in views if v[0] == item]
            best = max(mine, key=lambda v: (not v[2], v[1] if math.isfinite(v[1]) else -math.inf))
            out[item] = {"z": float(best[1]), "why": best[2], "idle": best[3], "part": part}
            if part in PARAM_ERRORS and _run_copies(item, values):
                # A correction free per run is there where the runs differ, too (gains 1.0003
                # and 1.0057 are each within the margin of the start plant's).
                apart = _per_run_significance(values, stderr, (item,))
                if out[item]["why"] and not apart["why"]:
                    out[item] = {**apart, "part": part}
    return out


def _run_copies(name: str, values: dict) -> bool:
    """Whether ``values`` hold run copies of ``name`` (``gamma_scale@2``)."""
    return any("@" in k and parameters.base_name(k) == name for k in values)


def _own(name: str, run: int, values: dict) -> str:
    """``name@run`` where the run has its own copy of the parameter, else ``name``."""
    return f"{name}@{run}" if f"{name}@{run}" in values else name


def _views(params, values, peaks):
    """(values, peaks, run) to judge a part at: once, or once per run for a part whose
    parameters are free per run (each run's own values and its own largest command)."""
    runs = sorted(
        {
            parameters.recording_of(k)
            for k in values
            if "@" in k and parameters.base_name(k) in params
        }
    )
    own = [
        i for i in runs if any(f"{n}@{i}" in values for n in params if n not in parameters.NUISANCE)
    ]
    if not own:
        yield values, peaks, None
        return
    for i in own:
        vals = {**values, **{n: values[f"{n}@{i}"] for n in params if f"{n}@{i}" in values}}
        pk = {k: peaks.get(f"{k}@{i}", v) for k, v in peaks.items() if "@" not in k}
        yield vals, pk, i


def _own_at_neutral(part, vals) -> bool:
    """Whether a parameter the part adds to what it stands on (``Effect.requires``) sits at
    the bound on its neutral side (``Param.neutral`` at or beyond it): the fit pushed the part
    to where it does nothing one would name, so the part is idle, not untestable, and the
    structure is judged without it (:meth:`~.search.Search.reduced`). A Stribeck fall at the
    least speed of its range is stiction's jump: on an independent cart with an extra 0.5 kg
    every better structure held Stribeck friction with v_stribeck at 0.1 mm/s, and a dead band
    was named instead."""
    below = {
        n for r in getattr(REGISTRY.get(part), "requires", ()) for n in effect_params().get(r, ())
    }
    for n in effect_params().get(part, ()):
        side = at_bound(n, vals[n]) if n not in below else ""
        neutral = parameters.spec(n).neutral if side else None
        if neutral is None:
            continue
        lo, hi = parameters.bounds(n)
        if (side == "lower" and neutral <= lo) or (side == "upper" and neutral >= hi):
            return True
    return False


def _bound_text(params, vals, per_run: bool) -> str:
    """Why a part's parameter at a bound makes it untestable ("" for none); a drive limit
    free per run may sit at its upper bound in a run it does not limit."""
    for n in params:
        side = at_bound(n, vals[n])
        if side and not (per_run and side == "upper"):
            return f"{n} = {vals[n]:.4g} sits at its {side} bound"
    return ""


def _judge(item, strength, weights, stderr, what, neutral, bound, gate=False) -> tuple:
    """(z, why, idle) of one item: its strength must act (be positive), be determined by the data
    (a standard error), and exceed the least size worth naming that its parameter declares
    (``Param.min_size``). z is the Wald statistic of the strength; with ``gate`` it must also
    exceed :data:`SIGNIFICANCE` (the drive limits' difference between runs). Whether an effect
    or a correction is there at all is decided by what it predicts (the search's selection by
    held-out prediction): a Wald test with standard errors widened for model error rejected
    Coulomb friction on a real P 50 step (z = 2.2) that predicts its end 2.6 times better.
    ``idle``: the strength does not act or is under the least size (the value is where the
    item does nothing one would name)."""
    se = stderr(weights)
    z = strength / se if se > 0 and math.isfinite(se) else math.nan
    if not math.isfinite(strength):
        z = math.inf if strength > 0 else math.nan
    least = _min_size(weights)
    if bound:
        return z, bound, False
    if not math.isfinite(z):
        return z, f"{what}: its standard error is not defined", False
    if strength <= 0:
        idle = "is within" if item in parameters.CORRECTABLE else "does not act: not past"
        return z, f"{what} {idle} {neutral}", True
    if gate and z <= SIGNIFICANCE:
        why = f"{what} is {z:.1f} standard errors from {neutral} ({SIGNIFICANCE:g} needed)"
        return z, why, False
    if least and strength < least:
        return (
            z,
            f"{what} is {strength:.3g} from {neutral}: under {least:g}, too small to matter",
            True,
        )
    return z, "", False


def _min_size(weights) -> float | None:
    """The least size worth naming of the strength's leading parameter, if it declares one."""
    name = parameters.base_name(next(iter(weights)))
    try:
        return parameters.spec(name).min_size
    except KeyError:
        return None


def _per_run_significance(values, stderr, names=None, peaks=None) -> dict:
    """Does the drive differ between runs? The largest difference between two runs' own values of
    a limit or of the gain (of ``names``; default all), as a Wald test (and beyond the
    limit's least size worth naming). A run whose own limit does not act (:func:`.per_run.acts`:
    at or above what the run drove, ``peaks``) says nothing of its limit and is left out;
    until 2026-12-06 every run counted, and such a run's value (at its bound, no standard
    error) kept the part from being named, so that one PI run under the limit beside the real
    cart's P 50 steps and PD run took the drive per run out of the diagnosis (docs/diagnose.md,
    "A run the diagnosis had not seen"). The cost, on the independent lab cart whose limit
    differs from run to run: its P 10 step's limit is named at 1.85 V, just under that run's
    2 V peak (the run's drive gain absorbed as a clipped peak), which the verdict flags as
    more than one drive's spread and :func:`.per_run.drive_runs` keeps out of the cart and
    of the next run's draw."""
    best = {"z": math.nan, "why": "nothing of the drive is free per run", "idle": False,
            "part": PER_RUN}  # fmt: skip
    for n in per_run_params() if names is None else names:
        own = {
            parameters.recording_of(k): v
            for k, v in values.items()
            if "@" in k and parameters.base_name(k) == n and acts(n, k, v, peaks or {})
        }
        if len(own) < 2:
            continue
        hi = max(own, key=own.get)
        lo = min(own, key=own.get)
        unit = f" {parameters.spec(n).unit}".rstrip()
        what = f"{n} from {own[lo]:.4g}{unit} (run {lo + 1}) to {own[hi]:.4g}{unit} (run {hi + 1})"
        z, why, _ = _judge(
            PER_RUN,
            own[hi] - own[lo],
            {f"{n}@{hi}": 1.0, f"{n}@{lo}": -1.0},
            stderr,
            what,
            "the same value in every run",
            "",
            gate=True,
        )
        if math.isnan(best["z"]) or (not why and best["why"]) or z > best["z"]:
            best = {"z": z, "why": why, "idle": False, "part": PER_RUN}
    return best


def implausible(values: dict, free, track: float | None = None) -> list:
    """Lines for fitted values a real cart of this lab does not have: any free parameter at
    the edge of its plausible range or at a bound of its fit (:func:`at_bound`: the data ask
    for a value beyond it), a spring's rest point off the track. Such values are never
    written into a plant file (:func:`tuning.estimation.diagnose.report.write_outputs`)."""
    if track is None:
        track = TRACK_LENGTH
    out = []
    for n in free:
        if n not in values or parameters.base_name(n) in parameters.NUISANCE:
            continue
        v = values[n]
        unit = plantspec.unit(parameters.base_name(n))
        unit = f" {unit}" if unit and unit != "1" else ""
        side = at_bound(n, v)
        rng = parameters.spec(n).plausible
        if side and rng is not None:
            out.append(
                f"{n} = {v:.4g}{unit} is outside what a cart of this lab has "
                f"({rng[0]:.3g}-{rng[1]:.3g}{unit}): the data ask for a value beyond it"
            )
        elif side:
            out.append(
                f"{n} = {v:.4g}{unit} sits at its {side} bound (the fit wanted a value "
                "beyond its range)"
            )
        elif (
            parameters.spec(n).unit == "m"
            and parameters.spec(n).neutral is None
            and abs(v) > track / 2
        ):
            out.append(f"{n} = {v:.4g} m is off the {track:g} m track")
    return out


def items(part) -> tuple:
    """The items a part names (:func:`significance`'s keys)."""
    if part == PER_RUN:
        return (PER_RUN,)
    return PARAM_ERRORS.get(part) or parameters.named_by(part)


def swap_tie(best, cands, plant, segments, base_plants, layout, memo, noise):
    """({}, None), or when ``best`` corrects M or gamma_scale and the structure with the other
    (values from :func:`~.structures.swapped_correction`, or its own fit where that scores
    better) is within :data:`TIE`: the facts for the verdict and that structure."""
    swap = swapped_correction(best.parts, best.values, plant)
    if swap is None:
        return {}, None
    parts, values = swap
    other = structure(parts, best.runs)
    keys = list(other.free) + [k for k in best.values if "@" in k]
    other.values = {k: values[k] for k in keys}
    other.residuals = exact_residuals(other, segments, base_plants, other.values, layout, memo)[0]
    other.rms_exact = rms(other.residuals)
    other.score = score(other, other.residuals, noise)
    fitted = next((c for c in cands if set(c.parts) == set(parts)), None)
    if fitted is not None and fitted.score < other.score:
        other = fitted
    if not other.score <= best.score + TIE:
        return {}, None
    pm = plant_of(best, base_plants, segments)
    ratios = {"gamma/m": float(pm.gamma / pm.m), "c/m": float(pm.c / pm.m)}
    corr = {c.corrections[0]: c for c in (best, other)}
    mass, gain = corr["mass"], corr["gain"]
    b_eq = sorted([best.values["B_eq"], other.values["B_eq"]])
    note = (
        "M and gamma_scale cannot be told apart from "
        + ("this recording" if len(segments) == 1 else "these recordings")
        + f": with B_eq free only gamma/m = {ratios['gamma/m']:.4g} N/(V kg) and c/m = "
        f"{ratios['c/m']:.4g} 1/s are identifiable (M = {mass.values['M']:.4g} kg with "
        f"B_eq = {mass.values['B_eq']:.4g} kg/s, or gamma_scale = "
        f"{gain.values['gamma_scale']:.4g} with B_eq = {gain.values['B_eq']:.4g} kg/s, fit "
        "equally well), so B_eq is not settled; diagnose a tap of the same cart with it "
        "(jaxcart diagnose RUN.toml TAP.toml) to separate them"
    )
    facts = {
        "parameters": ["M", "gamma_scale"],
        "ratios": ratios,
        "alternatives": [
            {
                "structure": c.name,
                "values": {k: v for k, v in c.values.items() if "@" not in k},
                "rms": c.rms_exact,
                "score": c.score,
                "implausible": implausible(c.values, c.free),
            }
            for c in (best, other)
        ],
        "B_eq": b_eq,
        "note": note,
    }
    return facts, other
