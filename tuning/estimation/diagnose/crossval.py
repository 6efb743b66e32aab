"""Leave one recording out: how well the chosen structure predicts a run it was not fitted to.

A joint diagnosis fits every recording of a cart at once; its RMS says how well the structure
*fits*. Whether it has captured the cart shows in how well it *predicts* a recording left out
of the fit. For each recording k of a joint diagnosis the chosen structure's shared values
(B_eq, f_c, ...) are re-fitted on the other recordings by the engine's exact-simulator
Gauss-Newton (:func:`tuning.estimation.engine.exact_polish.gauss_newton`), a few iterations
from the joint values, and recording k is simulated exactly with them:

- a value free per recording (a drive limit ``v_sat@2``) is unknown for a run left out: it is
  predicted by the median of the other runs' values, so the prediction error includes the
  run-to-run variation of the drive (what a new run of the cart would show);
- a tap's start state (``y0@k``, ``yd0@k``) is a property of that run, not of the cart: it is
  taken from the joint fit;
- where the other recordings cannot determine a shared value (the only driven run left out:
  nothing else moves a drive parameter) or give no value of a per-run parameter, recording k
  is predicted with the joint values and marked as not held out.

The runs are those the diagnosis made already (the search's :class:`~.core.ExactMemo`, seen
through each subset of recordings): the first Jacobian is one set of runs for all folds.
"""

from __future__ import annotations

import dataclasses
import math
import time as _time

import numpy as np

from tuning.estimation.diagnose import core as C
from tuning.estimation.engine import parameters as P
from tuning.estimation.engine.batch import Layout

#: Gauss-Newton iterations of each held-out re-fit. From the joint values the shared values
#: move little when one recording is dropped: on the five-recording benchmark cart 1, 2 and 3
#: iterations give the same predicted RMS to 4 digits; on the real tap and P 50 runs of a lab
#: cart 2 against 1 moved one by 0.4 % and 3 against 2 by 0.1 %.
ITERATIONS = 2
#: Gauss-Newton iterations of the driven runs' own fit (:func:`driven_alone`): it frees every
#: value of theirs, so it may move further from the joint values; the fit stops earlier where
#: a step falls under a hundredth of a standard error.
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
        layout = Layout(segments, search.layout.per_recording)
        return cls(order, cand, segments, plants, layout, _Through(search.memo, order))

    def values(self, values: dict) -> dict:
        """``values`` (diagnosis names) in the subset's names, those of other runs dropped."""
        return {_renamed(k, self.order): v for k, v in values.items() if _kept(k, self.order)}

    def residuals(self, values: dict) -> list:
        """Exact residuals [m] of the subset's recordings at ``values`` (subset names)."""
        return C.exact_residuals(
            self.cand, self.segments, self.plants, values, self.layout, self.memo
        )[0]


def _kept(name: str, order) -> bool:
    return "@" not in name or P.recording_of(name) in order


def _renamed(name: str, order) -> str:
    if "@" not in name:
        return name
    return f"{Layout.kind(name)}@{order.index(P.recording_of(name))}"


def _shared(best) -> list:
    """The chosen structure's shared free values (re-fitted in each fold)."""
    return [n for n in best.free if "@" not in n]


def impossible(best, segments, k: int) -> str:
    """Why recording ``k`` cannot be held out of ``best``'s fit ("" when it can): a shared
    value only the driven runs move (a drive parameter, gamma_scale) with no driven run left,
    or a value free per run of ``k`` that no other run has."""
    rest = [i for i in range(len(segments)) if i != k]
    if not any(segments[i].motor for i in rest):
        drive = [n for n in _shared(best) if P.is_drive(n)]
        if drive:
            return f"no other recording drives the cart, so none determines {', '.join(drive)}"
    for n in best.free:
        if "@" in n and P.recording_of(n) == k:
            kind = Layout.kind(n)
            if not any(f"{kind}@{i}" in best.values for i in rest):
                return f"no other recording has its own {kind}"
    return ""


def predicted_values(best, fitted: dict, k: int) -> dict:
    """The values recording ``k`` is predicted with (diagnosis names): the shared ``fitted``
    ones, each value free per run at the median of the other runs' values (a run's own drive
    limit is not known before it is fitted), ``k``'s start state from the joint fit."""
    out = dict(fitted)
    for n in best.free:
        if "@" in n and P.recording_of(n) == k:
            kind = Layout.kind(n)
            others = [
                v
                for key, v in best.values.items()
                if "@" in key and Layout.kind(key) == kind and P.recording_of(key) != k
            ]
            out[n] = float(np.median(others))
    for n in P.NUISANCE:
        if f"{n}@{k}" in best.values:
            out[f"{n}@{k}"] = best.values[f"{n}@{k}"]
    return out


def refit_without(best, search, k: int, iterations: int = ITERATIONS) -> dict:
    """``best``'s shared values re-fitted on every recording but ``k`` (Gauss-Newton on the
    exact simulator from the joint values; the other runs' own values and start states held
    at the joint ones). Returns {name: value} of the shared values."""
    shared = _shared(best)
    sub = Subset.of(best, search, [i for i in range(len(search.segments)) if i != k])
    held = sub.values({n: v for n, v in best.values.items() if "@" in n})

    def at(x):
        return {**held, **dict(zip(shared, (float(v) for v in x), strict=True))}

    def residual(x):
        return np.concatenate(sub.residuals(at(x)))

    def prefetch(xs):
        C.exact_prefetch(
            sub.cand, sub.segments, sub.plants, [at(x) for x in xs], sub.layout, sub.memo
        )

    done = C.exact_gauss_newton(
        best, shared, best.values, residual, search.segments, iterations, prefetch
    )
    return dict(zip(shared, (float(v) for v in done.x), strict=True))


def predict(best, search, k: int, values: dict) -> np.ndarray:
    """Recording ``k``'s exact residual [m] at ``values`` (diagnosis names)."""
    sub = Subset.of(best, search, [k])
    return sub.residuals(sub.values(values))[0]


def cross_validate(search, best, names, iterations: int = ITERATIONS) -> dict:
    """Leave each recording of a joint diagnosis out of ``best``'s fit and predict it.

    search: the finished :class:`~.search.Search`; best: the chosen structure; names: the
    recordings' names (as in ``per_recording``). Returns {} for a single recording, else the
    summary (see :func:`summary`) with "folds": per recording its "fitted_rms" (the joint
    fit's) and "predicted_rms" [m], "held_out" (False: predicted with the joint values,
    "why" says why), the shared "values" fitted without it and whether they "moved" from the
    joint ones (a re-fit that finds no descent from them keeps them)."""
    segments = search.segments
    if len(segments) < 2:
        return {}
    t0 = _time.perf_counter()
    why = [impossible(best, segments, k) for k in range(len(segments))]

    def fold(k):
        fitted = {n: best.values[n] for n in _shared(best)}
        if not why[k]:
            fitted = refit_without(best, search, k, iterations)
        r = predict(
            best, search, k, predicted_values(best, fitted, k) if not why[k] else best.values
        )
        return {**fitted, "_rms": C._rms([r])}, []

    done = C._spread(search.processes, list(range(len(segments))), fold)
    folds = []
    for k, (values, _) in enumerate(done):
        fitted_rms = C._rms([best.residuals[k]])
        predicted = values.pop("_rms")
        folds.append(
            {
                "recording": names[k],
                "fitted_rms": fitted_rms,
                "predicted_rms": predicted,
                "held_out": not why[k],
                "why": why[k],
                "values": values,
                # False where the re-fit found no descent from the joint values.
                "moved": any(v != best.values[n] for n, v in values.items()),
            }
        )
        search.say(
            f"  held out {names[k]}: fitted {fitted_rms * 1e3:.4g} mm, predicted "
            f"{predicted * 1e3:.4g} mm" + (f" (with the joint values: {why[k]})" if why[k] else "")
        )
    out = summary(best, folds, iterations)
    out["seconds"] = round(_time.perf_counter() - t0, 2)
    search.say(f"cross-validation (leave one recording out): {out['seconds']:.1f} s")
    return out


def driven_alone(search, best, iterations: int = DRIVEN_ITERATIONS) -> dict:
    """``best`` fitted on the driven runs alone, every motorless recording (a tap) left out:
    whether the closed-loop runs give the cart's B_eq the tap gives, under this model.

    The shared values and the runs' own (a drive limit free per run) are re-fitted by the exact
    Gauss-Newton from the joint values, through the search's memo. Returns {} without both a
    tap and a driven run, else {"recordings": their indices, "parameters": {shared name:
    {"value", "stderr", "unit"}}, "rms" [m]}; the standard errors are the engine's robust
    ones, widened for model error as the diagnosis's own are."""
    order = [i for i, seg in enumerate(search.segments) if seg.motor]
    if not order or len(order) == len(search.segments):
        return {}
    sub = Subset.of(best, search, order)
    values, jac, names, _ = C._polish(
        sub.cand, sub.segments, sub.plants, sub.values(best.values), sub.layout, iterations,
        memo=sub.memo,
    )  # fmt: skip
    residuals = sub.residuals(values)
    out = {"recordings": order, "parameters": {}, "rms": C._rms(residuals)}
    if jac is None:
        return out
    # The covariance takes the Jacobian per unit of each fitted coordinate (a log for some).
    slopes = np.array([P.value_slope(n, values[n]) for n in names])
    cov = C.covariance(sub.segments, names, values, jac * slopes, residuals, search.widen_above)
    for n in _shared(best):
        out["parameters"][n] = {
            "value": values[n],
            "stderr": cov.stderr({n: 1.0}),
            "unit": P.spec(n).unit,
        }
    return out


def summary(best, folds, iterations: int = ITERATIONS) -> dict:
    """The cross-validation's summary: "method", "iterations", "refitted" (the shared values
    re-fitted), "per_run_median" (values free per run, predicted by the others' median),
    "fitted_rms" and "predicted_rms" (over every recording held out [m]), "ratio", the
    "predicted_range" [m] of single recordings, "not_held_out" (names), "text" (one sentence,
    or "" with no recording held out), "folds"."""
    held = [f for f in folds if f["held_out"]]
    per_run = sorted({Layout.kind(n) for n in best.free if "@" in n})
    out = {
        "method": "leave one recording out",
        "iterations": iterations,
        "refitted": _shared(best),
        "per_run_median": per_run,
        "fitted_rms": math.nan,
        "predicted_rms": math.nan,
        "ratio": math.nan,
        "predicted_range": [math.nan, math.nan],
        "not_held_out": [f["recording"] for f in folds if not f["held_out"]],
        "text": "",
        "folds": folds,
    }
    if not held:
        return out
    fit = math.sqrt(np.mean([f["fitted_rms"] ** 2 for f in held]))
    pred = math.sqrt(np.mean([f["predicted_rms"] ** 2 for f in held]))
    lo, hi = min(f["predicted_rms"] for f in held), max(f["predicted_rms"] for f in held)
    out.update(fitted_rms=fit, predicted_rms=pred, ratio=pred / fit if fit > 0 else math.inf)
    out["predicted_range"] = [lo, hi]
    out["text"] = sentence(out)
    return out


def sentence(s: dict) -> str:
    """One short sentence for the verdict: the held-out prediction error beside the fit."""
    lo, hi = (x * 1e3 for x in s["predicted_range"])
    fits = [f["fitted_rms"] * 1e3 for f in s["folds"] if f["held_out"]]
    span = f"{lo:.2g} mm" if f"{lo:.2g}" == f"{hi:.2g}" else f"{lo:.2g}-{hi:.2g} mm"
    text = f"held out, each recording is predicted to {span} (fitted {min(fits):.2g}-"
    text += f"{max(fits):.2g} mm)"
    if s["per_run_median"]:
        text += f", its own {', '.join(s['per_run_median'])} taken as the other runs' median"
    return text


def annotate(per_recording: dict, cv: dict) -> None:
    """Each recording's entry of ``per_recording`` (in the diagnosis's order) with its
    "predicted_rms" [m] and "held_out" (and "held_out_why" where it was not)."""
    for entry, f in zip(per_recording.values(), cv.get("folds", []), strict=False):
        entry["predicted_rms"] = f["predicted_rms"]
        entry["held_out"] = f["held_out"]
        if f["why"]:
            entry["held_out_why"] = f["why"]
