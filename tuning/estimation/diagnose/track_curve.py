"""Friction read from the data as a curve of the position: the second shape the diagnosis's last
candidate tries (:mod:`.friction_curve`), where the recordings cover the track.

The curve (:mod:`jaxcart.effects.track_friction`: the kinetic friction as a smooth map f(y)
through its levels at knots 0.2 m apart over +/- 0.4 m) takes the place of Coulomb's one level
(f_c held at 0), beside the rest of the structure the speed curve keeps. It is tried where the
recordings together span :attr:`TrackFriction.covers` (two knot spacings), and it earns its
place as the speed curve does: by predicting recordings held out of its fit. Where the named
structure has no Coulomb friction, its dead band (friction's stand-in in closed loop) gives way
to the curve too. So that every fold
fits the same curve, the levels fitted are those at the knots within :data:`REACH` of the
stretch that every recording but one covers (all of them, with one recording); the others are
held, each at the nearest fitted level (:func:`fit_tied`). A level is the friction at its
knot, so the curve is read there, with the fit's standard errors. Friction along the track
never pushes (f_track >= 0).
"""

from __future__ import annotations

import math

import numpy as np

from jaxcart.effects import Deadzone, DeadzoneAsymmetry
from jaxcart.effects.track_friction import SPAN, TrackFriction
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.fit import fit

#: The drive's effects that stand in for friction's level in closed loop (the curve replaces
#: them where the named structure has no Coulomb friction).
STAND_INS = tuple(q.name for cls in (Deadzone, DeadzoneAsymmetry) for q in cls.params)
#: Friction at two knots apart by less than this [N] (or fewer standard errors of the
#: difference than MIN_Z) shows no friction that varies along the track.
MIN_VARIATION, MIN_Z = 0.02, 3.0
#: The knots of the curve (the effect's default size) and their spacing [m].
KNOTS = len(TrackFriction.f_track)
SPACING = 2 * SPAN / (KNOTS - 1)
#: A knot's level is fitted where the recordings come this close to it [m]: 3/8 of a spacing
#: (at half a spacing, a knot just beyond the runs' ends was fitted from their last few cm and
#: predicted a run held out 4 times worse than the named structure).
REACH = 0.375 * SPACING


def _span(recordings) -> tuple[float, float] | None:
    """(least, greatest) position [m] the ``recordings`` reach together, each run in the
    track's frame, from where it started."""
    ys = [np.asarray(r.position, dtype=float) for r in recordings]
    ys = [y for y in ys if y.size]
    return (min(float(y.min()) for y in ys), max(float(y.max()) for y in ys)) if ys else None


def covered(recordings) -> tuple[float, float] | None:
    """The stretch [m] the ``recordings`` cover together, or None where it is shorter than
    the curve needs (:attr:`TrackFriction.covers`)."""
    span = _span(recordings)
    return span if span and span[1] - span[0] >= TrackFriction.covers else None


def knots(n: int = KNOTS) -> np.ndarray:
    """The knots' positions [m]."""
    return np.linspace(-SPAN, SPAN, n)


def fitted_knots(recordings) -> tuple[int, ...]:
    """The knots whose levels the curve fits: within :data:`REACH` of the stretch that every
    recording but one covers (each held out in turn leaves it covered)."""
    folds = (
        [[r for j, r in enumerate(recordings) if j != i] for i in range(len(recordings))]
        if len(recordings) > 1
        else [recordings]
    )
    spans = [_span(f) for f in folds]
    if any(s is None for s in spans):
        return ()
    lo, hi = max(s[0] for s in spans), min(s[1] for s in spans)
    return tuple(k for k, q in enumerate(knots()) if lo - REACH <= q <= hi + REACH)


def structure(named, kept, fitted, initial: dict) -> tuple[tuple, dict]:
    """(parameters, values held) of the curve: ``kept`` (the speed curve's, the named drive
    and dry friction) with Coulomb's level given over to the levels at the ``fitted`` knots
    (f_c held at 0, every level starting at the named f_c [N]). Where the ``named`` structure
    has no Coulomb friction, the search put friction's level elsewhere: in closed loop a dead
    band of d volts resists as gamma d newtons would, so the curve takes its place too (held
    at 0)."""
    held = {"f_c": 0.0}
    if "f_c" not in named:
        held.update({n: 0.0 for n in STAND_INS if n in kept})
    start = TrackFriction.params[0].start
    # (a named f_c of 0 N starts the levels at the declared start too)
    level = float(initial.get("f_c") or start) if "f_c" in named else start
    held["f_track"] = (max(level, 0.01),) * KNOTS
    params = (*(n for n in kept if n not in held), *(f"f_track[{k}]" for k in fitted))
    return params, held


def fit_tied(recordings, params, *, initial, **options):
    """:func:`tuning.estimation.fit.fit` of the curve, twice where it holds levels: the
    second time from the first's values with each level held set to the nearest level fitted
    (beyond the recordings, friction as at the last knot they reach: a level held anywhere
    else bends the map at the edge of the stretch, and the fitted levels bend with it)."""
    first = fit(recordings, params, initial=initial, **options)
    fitted = [k for k in range(KNOTS) if f"f_track[{k}]" in params]
    if not fitted or len(fitted) == KNOTS:
        return first
    plant = next(s.plant for s in first.segments if "f_track" in s.plant.param_names())
    levels = [float(v) for v in plant.get("f_track")]
    tied = [levels[min(fitted, key=lambda j, k=k: abs(j - k))] for k in range(KNOTS)]
    values = {n: plant.get(n) for n in {base_name(q) for q in params} if n in plant.param_names()}
    return fit(recordings, params, initial={**initial, **values, "f_track": tuple(tied)}, **options)


def read(result, span) -> dict:
    """The friction along the track of a fit with f_track: {"positions" [m] and "levels" [N]
    of the knots it fitted, "bands" (their standard errors [N]), "covariance" [N^2], "knots"
    [m] and "knot_values" [N] (every level, the map itself), "span" (the stretch the
    recordings cover [m]), "b_eq" [kg/s]}."""
    plant = next(s.plant for s in result.segments if "f_track" in s.plant.param_names())
    values = [float(v) for v in plant.get("f_track")]
    where = knots(len(values))
    fitted = [k for k in range(len(values)) if _estimate(result, k) is not None]
    se = np.array([_estimate(result, k).stderr or 0.0 for k in fitted])
    corr = np.eye(len(fitted))
    for i, a in enumerate(fitted):
        for j, b in enumerate(fitted):
            if i != j:
                pair = (f"f_track[{a}]", f"f_track[{b}]")
                corr[i, j] = result.correlation.get(pair, result.correlation.get(pair[::-1], 0.0))
    return {
        "positions": [float(where[k]) for k in fitted],
        "levels": [values[k] for k in fitted],
        "bands": [float(s) for s in se],
        "covariance": (corr * np.outer(se, se)).tolist(),
        "knots": [float(q) for q in where],
        "knot_values": values,
        "span": [float(span[0]), float(span[1])],
        "b_eq": float(plant.get("B_eq")),
    }


def _estimate(result, k: int):
    e = result.params.get(f"f_track[{k}]")
    return e if e is not None and e.identifiable else None


def varies(track: dict) -> list:
    """The pairs of fitted knots whose friction differs by :data:`MIN_VARIATION` and
    :data:`MIN_Z` standard errors of the difference: [(y_a [m], y_b [m], difference [N], z)]."""
    q, v, cov = track["positions"], track["levels"], np.asarray(track["covariance"])
    out = []
    for a in range(len(q)):
        for b in range(a + 1, len(q)):
            diff = v[b] - v[a]
            se = math.sqrt(max(cov[a, a] + cov[b, b] - 2 * cov[a, b], 0.0))
            z = abs(diff) / se if se > 0 else math.inf
            if abs(diff) >= MIN_VARIATION and z >= MIN_Z:
                out.append((q[a], q[b], diff, z))
    return out


def describe(track: dict) -> str:
    """What the curve shows along the track, in words."""
    pairs = list(zip(track["positions"], track["levels"], strict=True))
    if len(pairs) < 2:
        return "the friction along the track is not determined by these recordings"
    (q_lo, v_lo), (q_hi, v_hi) = min(pairs, key=lambda x: x[1]), max(pairs, key=lambda x: x[1])
    (q0, v0), (q1, v1) = pairs[0], pairs[-1]
    return (
        f"along the track, friction goes from {v0:.2f} N at {q0:+.2f} m to {v1:.2f} N at "
        f"{q1:+.2f} m: least {v_lo:.2f} N at {q_lo:+.2f} m, most {v_hi:.2f} N at "
        f"{q_hi:+.2f} m (beside viscous B_eq {track['b_eq']:.3g} kg/s)"
    )
