"""Held out: how well a structure predicts what it was not fitted to, the test every part of a
diagnosis must pass to be named, and each recording's verdict.

A joint diagnosis fits every recording of a cart at once; its RMS says how well the structure
*fits*. Whether it has captured the cart shows in how well it *predicts* what was left out of
the fit (:func:`folds`):

- several recordings: each one left out in turn. The cart's values (B_eq, f_c, ...: shared)
  are re-fitted on the others by one Gauss-Newton step from the joint values on the exact
  simulator's Jacobian (:func:`one_step`, each recording weighed as in the joint fit); then the
  values that recording alone determines, its own drive limit and a tap's start state, are
  fitted to it (:func:`own_refit`): a run's drive state and a tap's push belong to that run,
  not to the cart, as system identification validates a model on a new experiment given its
  initial state. A shared value that only the recording left out determines (the only driven
  run: nothing else moves a drive parameter) stays at the joint fit's, and the recording is
  marked as not held out (:func:`impossible`);
- one recording: its stretches of equal motion, each held out of the fit to the rest.

:meth:`~tuning.estimation.diagnose.search.Search.select` drops every part whose structure does
not predict better than the one without it (the same criterion as the in-sample score), and
:func:`cross_validate` judges each recording by its held-out prediction: explained when within
what that experiment repeats (runs of the same experiment, :func:`~.scoring.repeat_levels`) or,
with no repeat, within :data:`~tuning.estimation.engine.noise.MISFIT_RATIO` times its encoder
floor.

The runs are those the diagnosis made already (the search's
:class:`~.exact_runs.ExactMemo`, seen through each subset of recordings).
"""

from __future__ import annotations

import dataclasses
import math
import time as _time

import numpy as np

from tuning.estimation.diagnose import candidate_runs, scoring
from tuning.estimation.engine import exact_runs, parameters
from tuning.estimation.engine.covariance import covariance
from tuning.estimation.engine.exact_polish import polish, values_jacobian
from tuning.estimation.engine.layout import Layout, for_candidates
from tuning.estimation.engine.least_squares import line_search, marquardt_step, minimize
from tuning.estimation.engine.noise import FLOOR_FACTOR, MISFIT_RATIO, RecordingNoise

#: Gauss-Newton iterations of a held-out recording's own values fitted to it (its drive limit,
#: a tap's start state: one or two values, from the joint fit's, close already).
ITERATIONS = 2
#: Damping of the held-out re-fit's Gauss-Newton step (Marquardt's, relative to the diagonal):
#: a direction that only the recording held out determined stays where the joint fit put it.
DAMPING = 1e-3
#: The shortest share of that step tried (halving from the whole step).
SHORTEST = 1 / 8
#: Gauss-Newton iterations of the driven runs' own fit (:func:`driven_alone`): it frees every
#: value of theirs, so it may move further from the joint values; the fit stops earlier where
#: a step falls under a tenth of a standard error (exact_polish.TOLERANCE).
DRIVEN_ITERATIONS = 6
#: The held-out prediction of a correct model is about its fit; above this many times the fit
#: the structure misses something that varies from run to run (said in the report).
WORSE = 1.5


class _Through:
    """The search's memo of single exact runs, seen from a subset of its recordings
    (``order``: the subset's positions in the diagnosis): a run keyed by its place in the
    subset is stored under its place in the diagnosis, so every fold reuses the runs the
    search and the other folds made. Whole-set results are not memoized here (keys by values
    alone would mix subsets)."""

    def __init__(self, memo, order):
        self.memo, self.order = memo, list(order)

    def segment(self, key, compute):
        return self.memo.segment(self._key(key), compute)

    def fill(self, jobs) -> None:
        self.memo.fill([(self._key(key), job) for key, job in jobs])

    def _key(self, key):
        return (self.order[key[0]], *key[1:])

    def get(self, cand, values, compute):
        del cand, values
        return compute()


@dataclasses.dataclass
class Subset:
    """The diagnosis restricted to the recordings ``order`` (their diagnosis indices), each
    per-recording name renumbered to its place in the subset (``v_sat@3`` -> ``v_sat@1``)."""

    order: list
    cand: object
    segments: list
    plants: list
    layout: Layout
    memo: object

    @classmethod
    def of(cls, best, search, order) -> Subset:
        order = list(order)
        cand = dataclasses.replace(
            best,
            free=tuple(_renamed(n, order) for n in best.free if _kept(n, order)),
            runs=tuple(order.index(r) for r in best.runs if r in order),
        )
        segments = [search.segments[i] for i in order]
        plants = [search.base_plants[i] for i in order]
        layout = for_candidates(segments, search.layout.per_recording)
        return cls(order, cand, segments, plants, layout, _Through(search.memo, order))

    def values(self, values: dict) -> dict:
        """``values`` (diagnosis names) in the subset's names, those of other runs dropped."""
        return {_renamed(k, self.order): v for k, v in values.items() if _kept(k, self.order)}

    def residuals(self, values: dict) -> list:
        """Exact residuals [m] of the subset's recordings at ``values`` (subset names)."""
        return candidate_runs.exact_residuals(
            self.cand, self.segments, self.plants, values, self.layout, self.memo
        )[0]


def _kept(name: str, order) -> bool:
    return "@" not in name or parameters.recording_of(name) in order


def _renamed(name: str, order) -> str:
    if "@" not in name:
        return name
    return f"{parameters.base_name(name)}@{order.index(parameters.recording_of(name))}"


def _shared(best) -> list:
    """The chosen structure's shared free values (re-fitted in each fold)."""
    return [n for n in best.free if "@" not in n]


def impossible(best, segments, k: int) -> str:
    """Why recording ``k`` cannot be held out of ``best``'s fit ("" when it can): a shared
    value only the driven runs move (a drive parameter, gamma_scale) with no driven run left,
    or a value free per run of ``k`` that no other run has."""
    rest = [i for i in range(len(segments)) if i != k]
    if not any(segments[i].motor for i in rest):
        drive = [n for n in _shared(best) if parameters.is_drive(n)]
        if drive:
            return f"no other recording drives the cart, so none determines {', '.join(drive)}"
    for n in best.free:
        if "@" in n and parameters.recording_of(n) == k:
            kind = parameters.base_name(n)
            if not any(f"{kind}@{i}" in best.values for i in rest):
                return f"no other recording has its own {kind}"
    return ""


def predict(best, search, k: int, values: dict) -> np.ndarray:
    """Recording ``k``'s exact residual [m] at ``values`` (diagnosis names)."""
    sub = Subset.of(best, search, [k])
    return sub.residuals(sub.values(values))[0]


#: A single recording is held out of its own fit in this many stretches of equal motion (path
#: length): each stretch predicted by the values fitted to the others.
BLOCKS = 5


@dataclasses.dataclass(frozen=True)
class Fold:
    """What one fit leaves out: recording ``recording``, all of it (``rows`` None: several
    recordings, leave one out) or the samples ``rows`` of it (one recording, a stretch)."""

    recording: int
    rows: np.ndarray | None = None


def folds(segments) -> list[Fold]:
    """Leave one recording out of several; one recording's stretches of equal path length
    (:data:`BLOCKS`), each held out in turn (a stretch of a run whose cart moves is worth as
    much as any other, wherever the run spends its time at rest)."""
    if len(segments) > 1:
        return [Fold(k) for k in range(len(segments))]
    y = np.asarray(segments[0].target, dtype=float)
    path = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(y)))])
    if path[-1] <= 0:
        return [Fold(0, np.arange(y.size))]
    edges = np.searchsorted(path, path[-1] * np.arange(1, BLOCKS) / BLOCKS)
    return [Fold(0, rows) for rows in np.split(np.arange(y.size), edges) if rows.size]


def _names_of(search, c) -> list:
    """``c``'s free values and the nuisances it has values of (a tap's start state)."""
    return list(c.free) + [n for n in search.nuis if n in c.values]


def exact_jacobian(search, c) -> np.ndarray:
    """The exact simulator's forward-difference Jacobian of ``c``'s residual (every recording's
    rows, in order) at its values, per unit of each of :func:`_names_of`'s values (memoized on
    ``c`` by its values)."""
    key = exact_runs.values_key(c.values)
    if c.jac_exact[0] == key:
        return c.jac_exact[1]
    names = _names_of(search, c)

    def at(x):
        return {**c.values, **dict(zip(names, (float(v) for v in x), strict=True))}

    def residuals(xs):
        search.prefetch([(c, at(x)) for x in xs])  # the runs of every point made at once
        return [np.concatenate(search.exact(c, at(x))[0]) for x in xs]

    jac = values_jacobian(
        residuals,
        names,
        [c.values[n] for n in names],
        reference=candidate_runs.smooth_reference(c, names, c.values, search.segments),
    )
    c.jac_exact = (key, jac)
    return jac


def one_step(search, c, fold: Fold) -> dict:
    """``c``'s values re-fitted without ``fold``: one Gauss-Newton step from the joint values on
    the exact Jacobian (:func:`exact_jacobian`), each recording weighed as in the joint fit,
    within the bounds, halved until the cost of what is fitted falls (a step the linearisation
    overshoots, Coulomb friction without the stretch where the cart stops, is not taken
    whole; none that falls: the joint values). The values that only what is held out
    determines (a run's own drive limit, a tap's start state) stay at the joint fit's
    (:func:`own_refit` fits them)."""
    names = _names_of(search, c)
    jac = exact_jacobian(search, c)
    weights = search.noise.weights(c.residuals)
    keep, root = [], []
    for i, (seg, w) in enumerate(zip(search.segments, weights, strict=True)):
        held = np.zeros(seg.target.size, dtype=bool)
        if i == fold.recording:
            held[slice(None) if fold.rows is None else fold.rows] = True
        root.append(np.full(seg.target.size, math.sqrt(w)))
        keep.append(~held)
    keep, root = np.concatenate(keep), np.concatenate(root)

    def fitted(values):  # the weighted residual of what is fitted
        return np.concatenate(search.exact(c, values)[0])[keep] * root[keep]

    def at(x):
        return {**c.values, **dict(zip(names, (float(v) for v in x), strict=True))}

    solver = line_search(
        bounds=tuple(np.array([parameters.bounds(n)[k] for n in names]) for k in (0, 1)),
        shortest=SHORTEST,
        tolerance=None,
        direction=lambda j, r: marquardt_step(j.T @ j, j.T @ r, DAMPING),
    )
    start = solver.init(
        np.array([c.values[n] for n in names]), fitted(c.values), jac[keep] * root[keep, None]
    )
    end = minimize(solver, lambda xs: ([fitted(at(x)) for x in xs], None), start, 1)
    return at(end.x) if end.cost < start.cost else dict(c.values)


def own_names(search, c, k: int) -> list:
    """The values of ``c`` that recording ``k`` alone determines: its own copies of the values
    free per run (a drive limit) and a tap's start state."""
    return [n for n in _names_of(search, c) if "@" in n and parameters.recording_of(n) == k]


def own_refit(search, c, k: int, values: dict, iterations: int = ITERATIONS) -> dict:
    """``values`` with recording ``k``'s own values (:func:`own_names`) fitted to it alone by
    the exact Gauss-Newton, the cart's values held: a run's drive state and a tap's push are
    properties of that run, not of the cart, and a run held out of the cart's fit is predicted
    given them, as system identification validates a model on a new experiment."""
    own = own_names(search, c, k)
    if not own:
        return values
    sub = Subset.of(c, search, [k])
    renamed = [_renamed(n, [k]) for n in own]
    held = sub.values(values)

    def at(x):
        return {**held, **dict(zip(renamed, (float(v) for v in x), strict=True))}

    def residuals(xs):
        candidate_runs.exact_prefetch(  # the runs of every point made at once
            sub.cand, sub.segments, sub.plants, [at(x) for x in xs], sub.layout, sub.memo
        )
        return [sub.residuals(at(x))[0] for x in xs]

    done = polish(
        residuals, renamed, [held[n] for n in renamed], iterations,
        reference=candidate_runs.smooth_reference(sub.cand, renamed, held, sub.segments),
    )  # fmt: skip
    return {**values, **dict(zip(own, (float(v) for v in done.x), strict=True))}


def held_out(search, c) -> tuple[list, list]:
    """Each recording's residual [m] predicted out of ``c``'s fit (:func:`folds`): the cart's
    values re-fitted without it (:func:`one_step`), then its own values fitted to it
    (:func:`own_refit`). Returns (one array per recording, every sample predicted by the fit
    that left it out; per recording the values [SI] of the fit that left all of it out, None
    for a single recording's stretches)."""
    out = [np.full(s.target.size, np.nan) for s in search.segments]
    values_of = [None] * len(search.segments)
    for fold in folds(search.segments):
        values = one_step(search, c, fold)
        if fold.rows is None:
            values = own_refit(search, c, fold.recording, values)
            values_of[fold.recording] = values
        r = predict(c, search, fold.recording, values)
        if fold.rows is None:
            out[fold.recording] = r
        else:
            out[fold.recording][fold.rows] = r[fold.rows]
    return out, values_of


def cross_validate(search, best, names, levels) -> dict:
    """Every recording of ``best`` predicted out of its fit (:meth:`~.search.Search.held_score`)
    beside its fit, and judged.

    names: the recordings' names; levels: {recording index: what that experiment repeats [m]}
    (:func:`~.scoring.repeat_levels`). Returns the summary: "method", "refitted" (the cart's
    values re-fitted), "own" (values fitted to each recording held out), "fitted_rms" and
    "predicted_rms" over the recordings [m], "ratio", "predicted_range" [m], "not_held_out"
    (names), "text" (one sentence), "explained" (every recording within its level) and
    "folds": per recording its "fitted_rms", "predicted_rms" [m], "held_out" (False: a value
    only it determines stayed at the joint fit's, "why" says which), "floor" [m], "level" [m]
    (what it is judged against), "repeat" [m] or None, "judged_by" ("held out"; "fit" for a
    single recording), "judged_rms" [m], "explained" and "values" (the fit that left it out,
    {name: value [SI]} in the diagnosis's names; None where it was not held out whole)."""
    t0 = _time.perf_counter()
    search.held_score(best)
    predicted, values_of = best.held["residuals"], best.held["values"]
    segments = search.segments
    folds = []
    for k in range(len(segments)):
        why = impossible(best, segments, k) if len(segments) > 1 else ""
        floor = float(search.noise.floors[k]) / FLOOR_FACTOR
        repeat = levels.get(k)
        level = max(MISFIT_RATIO * floor, repeat or 0.0)
        # A single recording is judged by its fit: its stretches carry what the rest lacks
        # (where a Coulomb cart stops fixes f_c), so even the truth predicts the last one at
        # 3 times its fit; its held-out prediction chooses what is named and is shown.
        judged = best.residuals[k] if len(segments) == 1 else predicted[k]
        folds.append(
            {
                "recording": names[k],
                "fitted_rms": scoring.rms([best.residuals[k]]),
                "predicted_rms": scoring.rms([predicted[k]]),
                "held_out": not why,
                "why": why,
                # The cart fitted without it (its own drive values fitted to it): what
                # predicts it, for a design's model error (tuning.design.calibration).
                "values": None
                if why or values_of[k] is None
                else {n: float(v) for n, v in values_of[k].items()},
                "floor": floor,
                "repeat": repeat,
                "level": level,
                "judged_rms": scoring.rms([judged]),
                "judged_by": "fit" if len(segments) == 1 else "held out",
                "explained": scoring.rms([judged]) <= level,
            }
        )
    out = summary(best, folds, single=len(segments) == 1)
    out["seconds"] = round(_time.perf_counter() - t0, 2)
    for f in folds:
        search.say(
            f"  held out {f['recording']}: fitted {f['fitted_rms'] * 1e3:.4g} mm, predicted "
            f"{f['predicted_rms'] * 1e3:.4g} mm, "
            + ("within" if f["explained"] else "beyond")
            + f" {f['level'] * 1e3:.3g} mm ("
            + ("what it repeats" if f["repeat"] else f"{MISFIT_RATIO:g} times its encoder floor")
            + ")"
            + (f" (with the joint values: {f['why']})" if f["why"] else "")
        )
    return out


def summary(best, folds, single: bool = False) -> dict:
    """The held-out summary of :func:`cross_validate` from its ``folds``."""
    held = [f for f in folds if f["held_out"]] or folds
    fit = math.sqrt(np.mean([f["fitted_rms"] ** 2 for f in held]))
    pred = math.sqrt(np.mean([f["predicted_rms"] ** 2 for f in held]))
    out = {
        "method": (
            f"each of {BLOCKS} stretches of equal motion held out of the fit to the rest"
            if single
            else "leave one recording out; its own drive values and start state fitted to it"
        ),
        "refitted": _shared(best),
        "own": sorted({parameters.base_name(n) for n in best.free if "@" in n}),
        "fitted_rms": fit,
        "predicted_rms": pred,
        "ratio": pred / fit if fit > 0 else math.inf,
        "predicted_range": [
            min(f["predicted_rms"] for f in held),
            max(f["predicted_rms"] for f in held),
        ],
        "not_held_out": [f["recording"] for f in folds if not f["held_out"]],
        "explained": all(f["explained"] for f in folds),
        "folds": folds,
    }
    out["text"] = sentence(out, single)
    return out


def sentence(s: dict, single: bool = False) -> str:
    """One short sentence for the verdict: the held-out prediction beside the fit."""
    if single:
        f = s["folds"][0]
        return (
            f"held out stretch by stretch, the recording is predicted to "
            f"{f['predicted_rms'] * 1e3:.2g} mm (fitted {f['fitted_rms'] * 1e3:.2g} mm)"
        )
    lo, hi = (x * 1e3 for x in s["predicted_range"])
    fits = [f["fitted_rms"] * 1e3 for f in s["folds"] if f["held_out"]] or [math.nan]
    span = f"{lo:.2g} mm" if f"{lo:.2g}" == f"{hi:.2g}" else f"{lo:.2g}-{hi:.2g} mm"
    text = f"held out, each recording is predicted to {span} (fitted {min(fits):.2g}-"
    text += f"{max(fits):.2g} mm)"
    if s["own"]:
        text += f", its own {', '.join(s['own'])} fitted to it"
    return text


def annotate(per_recording: dict, cv: dict) -> None:
    """Each recording's entry of ``per_recording`` (in the diagnosis's order) with its
    "predicted_rms" [m], "held_out" (and "held_out_why" where it was not), the "level" [m] it
    is judged against and whether it is "explained"."""
    for entry, f in zip(per_recording.values(), cv.get("folds", []), strict=False):
        entry["predicted_rms"] = f["predicted_rms"]
        entry["held_out"] = f["held_out"]
        entry["level"] = f["level"]
        entry["explained"] = f["explained"]
        if f["why"]:
            entry["held_out_why"] = f["why"]


def driven_alone(search, best, iterations: int = DRIVEN_ITERATIONS) -> dict:
    """``best`` fitted on the driven runs alone, every motorless recording (a tap) left out:
    whether the closed-loop runs give the cart's B_eq the tap gives, under this model
    (:func:`fitted_apart`)."""
    return fitted_apart(search, best, True, iterations)


def taps_alone(search, best, iterations: int = DRIVEN_ITERATIONS) -> dict:
    """``best``'s cart values fitted on the motorless recordings (taps) alone, every driven
    run left out (:func:`fitted_apart`; the drive's values act nowhere there)."""
    return fitted_apart(search, best, False, iterations)


def fitted_apart(search, best, motor: bool, iterations: int = DRIVEN_ITERATIONS) -> dict:
    """``best`` fitted on the recordings whose motor is (``motor``) or is not connected alone:
    the shared values and the recordings' own (a drive limit per run, a tap's start state)
    re-fitted by the exact Gauss-Newton from the joint values, each recording weighed by its
    own misfit, through the search's memo. Returns {} unless the diagnosis has recordings of
    both kinds, else {"recordings": their indices, "parameters": {shared name: {"value",
    "stderr", "unit"}} (the cart's alone for taps), "rms" [m]}; the standard errors are the
    engine's robust ones, widened for model error as the diagnosis's own are."""
    order = [i for i, seg in enumerate(search.segments) if seg.motor == motor]
    if not order or len(order) == len(search.segments):
        return {}
    sub = Subset.of(best, search, order)
    start = sub.values(best.values)
    noise = RecordingNoise(sub.segments, FLOOR_FACTOR)
    values, jac, names, _ = candidate_runs.polish(
        sub.cand, sub.segments, sub.plants, start, sub.layout, iterations, memo=sub.memo,
        weights=noise.weights(sub.residuals(start)),
    )  # fmt: skip
    residuals = sub.residuals(values)
    out = {"recordings": order, "parameters": {}, "rms": scoring.rms(residuals)}
    if jac is None:
        return out
    # The covariance takes the Jacobian per unit of each fitted coordinate (a log for some).
    slopes = np.array([parameters.value_slope(n, values[n]) for n in names])
    cov = covariance(
        sub.segments, names, values, jac * slopes, residuals, search.widen_above,
        noise.weights(residuals),
    )  # fmt: skip
    for n in _shared(best):
        if motor or not parameters.is_drive(n):
            out["parameters"][n] = {
                "value": values[n],
                "stderr": cov.stderr({n: 1.0}),
                "unit": parameters.spec(n).unit,
            }
    return out
