"""The diagnosis's verdict on a finished search (:class:`~.search.Search`): the structure
named (:func:`named`: the lead of :meth:`~.search.Search.choose`, its parts kept by held-out
prediction, its near-ties and the better-scoring parts not named), its values with standard
errors, what may be missing where it does not explain the recordings, and the
:class:`~.result.Diagnosis` that says it all (:func:`diagnosis`).
"""

from __future__ import annotations

import math
import time as _time

import numpy as np

from jaxcart import plantspec
from tuning.estimation.diagnose import crossval, locate, per_run, scoring, significance
from tuning.estimation.diagnose.policy import K_MAX, TIE
from tuning.estimation.diagnose.result import Diagnosis, _times
from tuning.estimation.diagnose.structures import PARAM_ERRORS
from tuning.estimation.engine import parameters
from tuning.estimation.engine.noise import effective_samples
from tuning.estimation.fitting.names import plant_values
from tuning.estimation.fitting.result import Estimate, FitResult, SegmentFit


def named(search):
    """(the structure named, near-ties, effects of better-scoring structures not named,
    M/gamma_scale not told apart)."""
    cands = search.cands
    search.unearned = []
    best = search.select(search.choose(cands))
    scoring.window_evidence(cands, search.round1[0], search.masks)
    for c in cands:
        search.eligible(c)  # every candidate's significance at its final values
    ranks = _ranks(cands)
    rank, leader = ranks[id(best)]
    ties = [
        c
        for c in cands
        if c is not best
        and search.eligible(c)
        and (
            ranks[id(c)][0] <= rank + TIE or _one_path(ranks[id(c)][1], leader, search.noise.floors)
        )
        and best.parts
        and c.parts
        and len(c.parts) <= len(best.parts)
        and set(c.parts) != set(best.parts)
        and (set(c.effects) != set(best.effects) or not best.effects)
        and not (set(best.parts) < set(c.parts))
    ]
    dropped = [
        {"structure": c.name, "effect": k, "z": c.z.get(k, math.nan), "why": why}
        for c in sorted(cands, key=lambda c: c.score)
        if c.score < rank
        for k, why in c.why.items()
        if why
    ]
    for item in dropped:
        search.say(f"  not named: {item['effect']} of {item['structure']} ({item['why']})")
    # M or gamma_scale corrected: the other may fit as well (only ratios are identifiable).
    unident, swapped = significance.swap_tie(
        best, cands, search.ref_plant, search.segments, search.base_plants, search.layout,
        search.memo, search.noise,
    )  # fmt: skip
    if swapped is not None:
        ties = [c for c in ties if set(c.parts) != set(swapped.parts)]
        best = _plausible_of(search, best, swapped)
    return best, ties, dropped, unident


def _ranks(cands) -> dict:
    """{id of a structure: (the score it ranks by, the structure that scored it)}: its own, or
    a structure's that is it with idle parts (:meth:`~.search.Search.reduced`), where that is
    lower. A dead band and a drive offset are one model on a step that moves one way: with M
    free (idle, at 0.2 % of the start plant's) both fit to 0.0093 mm, and the one named must
    find the other a tie."""
    out = {id(c): (c.score, c) for c in cands}
    by_parts = {}
    for c in cands:
        by_parts.setdefault(frozenset(c.parts), []).append(c)
    for d in cands:
        if d.idle:
            for c in by_parts.get(frozenset(d.parts) - set(d.idle), ()):
                out[id(c)] = min(out[id(c)], (d.score, d), key=lambda x: x[0])
    return out


def _one_path(a, b, floors) -> bool:
    """Whether structures ``a`` and ``b`` (each at its fitted values) simulate every recording
    along one path: their exact runs differ by less than the criterion's floor of that
    recording (RMS, ``floors`` [m]), under which a residual explains nothing. They are then
    one model on these recordings whatever their scores: on the independent generator's
    0.4 V dead band under a P step whose command never fell below 0.39 V, the dead band and
    a -0.40 V drive offset (each with M idle) ran 0.0026 mm apart, under the criterion's
    floor of 0.0099 mm, yet the offset scored 36 lower (the dead band's fit sits on its
    corner at the run's end) and was named alone."""
    if not a.residuals or not b.residuals:
        return False
    return all(
        np.sqrt(np.mean((np.asarray(ra) - np.asarray(rb)) ** 2)) < f
        for ra, rb, f in zip(a.residuals, b.residuals, floors, strict=True)
    )


def _plausible_of(search, best, swapped):
    """Of two structures that fit equally well, the one whose values a cart of this lab
    has (a heavier cart with a plausible B_eq rather than a weaker motor with B_eq near 0)."""
    if not significance.implausible(best.values, best.free) or significance.implausible(
        swapped.values, swapped.free
    ):
        return best
    if swapped.jac is None:  # values mapped from best's: an exact re-fit gives its own
        values, arrays, _ = search.polished(swapped, dict(swapped.values))
        swapped.jac = arrays[-1]
        if search.better(arrays[:-1], swapped):
            swapped.values, swapped.residuals = values, arrays[:-1]
            swapped.rms_exact = scoring.rms(swapped.residuals)
            swapped.score = scoring.score(swapped, swapped.residuals, search.noise)
    return swapped if swapped.jac.size and search.eligible(swapped) else best


def _parameters(search, best, cov, unident) -> tuple[dict, dict]:
    """(the named structure's shared values with standard errors, the baseline's B_eq)."""
    params = {}
    for n in best.free:
        if "@" in n:
            continue  # per recording: in the per-recording results
        params[n] = {
            "value": best.values[n],
            "stderr": cov.stderr({n: 1.0}),
            "unit": plantspec.unit(n),
            "stderr_widened": cov.widened,
        }
    if unident:
        params["B_eq"]["settled"] = False
        params["B_eq"]["range"] = unident["B_eq"]
    base = search.round1[0]
    base_cov = search.cov_of(base)
    baseline = {
        "B_eq": {
            "value": base.values["B_eq"],
            "stderr": base_cov.stderr({"B_eq": 1.0}),
            "unit": "kg/s",
            "stderr_widened": base_cov.widened,
        },
        "rms": base.rms_exact,
    }
    return params, baseline


def _misfit(search, best, cv) -> tuple[list, str]:
    """(what may be missing, which recordings the best structure does not explain and by
    how much) from its held-out summary ``cv``."""
    if cv["explained"]:
        return [], ""
    left = locate.residual_tests(
        search.segments, best.residuals, search.commands, search.noise.total
    )
    beyond = [f for f in cv["folds"] if not f["explained"]]
    text = f"the best structure ({best.name}) leaves " + "; ".join(
        (
            f"{f['recording']} predicted to {f['predicted_rms'] * 1e3:.3g} mm held out "
            f"(fitted {f['fitted_rms'] * 1e3:.3g} mm), "
            if f["judged_by"] == "held out"
            else f"{f['recording']} fitted to {f['fitted_rms'] * 1e3:.3g} mm (held out "
            f"stretch by stretch {f['predicted_rms'] * 1e3:.3g} mm), "
        )
        + (
            f"{f['judged_rms'] / f['repeat']:.2g} times what that run repeats "
            f"({f['repeat'] * 1e3:.3g} mm)"
            if f["repeat"]
            else f"{_times(f['judged_rms'] / f['floor'])} times its encoder floor "
            f"{f['floor'] * 1e3:.2g} mm, and no repeat of that run to compare with"
        )
        for f in beyond
    )
    text += "; the standard errors are widened for model error"
    search.say(text)
    return suggestions(left, best), text


def diagnosis(search, names, checks, t_start) -> Diagnosis:
    """The :class:`Diagnosis` of the finished search."""
    best, ties, dropped, unident = named(search)
    base, segments = search.round1[0], search.segments
    cov = search.cov_of(best)
    params, baseline = _parameters(search, best, cov, unident)
    traces = [
        {
            "name": seg.name,
            "time": seg.time,
            "measured": seg.target,
            "baseline": seg.target + rb,
            "after": seg.target + ra,
        }
        for seg, rb, ra in zip(segments, base.residuals, best.residuals, strict=True)
    ]
    level = max(search.repeat.values()) if search.repeat else None
    peaks = search.peaks(best)
    per_recording = per_run.per_recording(best, names, segments, base, cov, peaks)
    # Judged by prediction: each recording (each stretch of a single one) held out of the
    # fit and predicted, against what that experiment repeats or its encoder floor.
    cv = crossval.cross_validate(search, best, list(per_recording), search.repeat)
    crossval.annotate(per_recording, cv)
    explained = cv["explained"]
    suggestions, misfit = _misfit(search, best, cv)
    corrections = [PARAM_ERRORS[p][0] for p in best.corrections]
    driven, taps = crossval.driven_alone(search, best), crossval.taps_alone(search, best)
    for apart in (driven, taps):
        if apart:
            apart["recordings"] = [list(per_recording)[i] for i in apart["recordings"]]
    plant = per_run.cart_plant(best, search.base_plants, segments, peaks)
    seconds = elapsed(t_start)
    # Every structure's fit as a fit reports one; the named one's with its held-out folds.
    for c in search.cands:
        c.result = (
            _fit(search, best, seconds, cov, plant, peaks, cv, misfit)
            if c is best
            else _fit(search, c, seconds)
        )
    return Diagnosis(
        names,
        "diagnosed",
        [],
        checks,
        left_out=list(best.effects),
        corrected_parameters=corrections,
        equivalent=[list(c.effects) or [PARAM_ERRORS[p][0] for p in c.corrections] for c in ties],
        rms_before=base.rms_exact,
        rms_after=best.rms_exact,
        floor=search.floor,
        parameters=params,
        baseline=baseline,
        windows=search.wins,
        tests=search.tests,
        candidates=sorted(search.cands, key=lambda c: c.score),
        chosen=best.name,
        plant=plant,
        seconds=seconds,
        traces=traces,
        explained=explained,
        misfit=misfit,
        suggestions=suggestions,
        # a drive limit above what its run drove is not that run's value (at a bound or not)
        implausible=significance.implausible(
            best.values,
            [
                k
                for k in best.free
                if per_run.acts(parameters.base_name(k), k, best.values[k], peaks)
            ],
        ),
        not_significant=dropped,
        significance=dict(best.z),
        unidentifiable=unident,
        start_values={n: search.neutral[n] for n in corrections},
        per_recording=per_recording,
        drive_spread=per_run.per_run_inconsistency(best.values, peaks) if best.runs else "",
        cross_validation=cv,
        driven_alone=driven,
        taps_alone=taps,
        repeat=level,
        remainder=remainder(best, segments),
    )


def _fit(search, c, seconds, cov=None, plant=None, peaks=None, cv=None, misfit="") -> FitResult:
    """Structure ``c``'s fit as every fit reports one (the cart a command takes from a
    diagnosis instead of fitting again): its shared values and each run's own (``v_sat@2``,
    where the limit says what the drive does: :func:`per_run.drive_runs`; the drawn runs of a
    design, :func:`tuning.design.uncertainty.from_fit`) with standard errors, each recording's exact
    runs before (the handout's model, B_eq fitted) and after, the values of the fit that left
    it out (:attr:`SegmentFit.held_out`, from ``cv``'s folds: the named structure's), and the
    fitted cart, effects included. ``cov``, ``plant``, ``peaks``: where the caller has them."""
    cov = search.cov_of(c) if cov is None else cov
    peaks = search.peaks(c) if peaks is None else peaks
    if plant is None:
        plant = per_run.cart_plant(c, search.base_plants, search.segments, peaks)
    own = [k for k in c.free if "@" in k and parameters.base_name(k) not in parameters.NUISANCE]
    names = [n for n in c.free if "@" not in n]
    drive = per_run.drive_runs(c.values, peaks)
    names += [
        k
        for k in sorted(own, key=parameters.recording_of)  # recording by recording
        if k in drive
    ]
    params = {n: Estimate(n, float(c.values[n]), cov.stderr({n: 1.0})) for n in names}
    folds = (cv or {}).get("folds") or [{}] * len(search.segments)
    segments = []
    for seg, rb, ra, fold in zip(
        search.segments, search.round1[0].residuals, c.residuals, folds, strict=True
    ):
        before, after = seg.target + rb, seg.target + ra
        segments.append(
            SegmentFit(
                seg.name,
                seg.kind,
                seg.time,
                seg.target,
                before,
                after,
                before,
                after,
                {},
                plant,
                fold.get("values"),
            )
        )
    return FitResult(
        params=params,
        values=plant_values(plant, [n for n in params if "@" not in n]),
        segments=segments,
        correlation={},
        n_data=sum(s.measured.size for s in segments),
        seconds=seconds,
        smoothing=None,
        exact_polish=True,
        noise_floor=search.floor,
        n_effective=effective_samples(c.residuals),
        misfit=misfit,
        cart=plant,
    )


#: What a residual that still correlates with each signal after the best structure may point
#: to beyond the candidates (the suggestions of a diagnosis that explains nothing).
BEYOND = {
    "position": "a force that varies along the track (friction: jaxcart diagnose --curve reads "
    "it as a curve of the position where the recordings cover 0.4 m; jaxcart fit --params "
    "B_eq,f_track)",
    "sign_velocity": "friction beyond Coulomb and stiction (speed-dependent: jaxcart diagnose "
    "--curve reads it as a curve of the speed) or backlash (jaxcart fit --params B_eq,backlash)",
    "command": "a drive nonlinearity beyond saturation, deadzone and current limit",
    "acceleration": "inertia or lag beyond M and delay (the motor's electrical lag)",
}


def suggestions(tests, best) -> list:
    """What may be missing when nothing explains the recording: the signals the best
    structure's residual still correlates with (:data:`BEYOND`), more effects at once,
    physics outside the library."""
    out = [
        BEYOND[k] + f" (its residual correlates with {k.replace('_', ' ')}, z = {t['z']:+.0f})"
        for k, t in tests.items()
        if k in BEYOND and t.get("significant")
    ]
    n = len(best.free) - 1
    out.append(
        f"more effects at once than the search combines ({n} parameters here, at most {K_MAX - 1})"
        if n >= K_MAX - 2
        else "more effects at once"
    )
    out.append("physics outside the effects library")
    return out


def remainder(best, segments) -> str:
    """The best structure's residual in words, on the segment where most of it is left."""
    k = max(range(len(segments)), key=lambda i: float(np.sum(best.residuals[i] ** 2)))
    text = locate.describe_residual(best.residuals[k], float(segments[k].experiment.sample_time))
    return text + (f" (in {segments[k].name})" if len(segments) > 1 else "")


def elapsed(t0) -> float:
    """Seconds since ``t0`` (a ``time.perf_counter()`` reading), to 10 ms."""
    return round(_time.perf_counter() - t0, 2)
