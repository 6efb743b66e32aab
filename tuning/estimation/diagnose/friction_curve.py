"""Friction read from the data as a curve of the speed: the diagnosis's last candidate, where no
named structure explains the recordings (``jaxcart diagnose --curve``).

The curve (:mod:`jaxcart.effects.friction_curve`: the sliding friction's departure from its slow
level at 20, 80 and 320 mm/s, each direction the cart slid) takes the place of the named
structure's forces other than dry friction (viscous friction by direction, a spring, a tilt: what
a search reaches for where friction's shape is missing) and keeps the rest (the drive's limits, a
delay, Coulomb friction and its asymmetry at the slow end). It is a table of up to six values,
so it always fits better; it earns its place as every named effect does, by predicting what it
was not fitted to: each recording left out in turn, both structures fitted to the others from
their joint fits' values and each predicting it (its own drive values and start state fitted to
it, as :mod:`.crossval` does); a recording counts only where the others determine every value.
The curve is named where its held-out sum of squares is at most
:data:`HELD_OUT_SHARE` of the named structure's and some entry departs from the slow level by
:data:`MIN_DEPARTURE` and :data:`MIN_Z` standard errors; with one recording nothing is held out
and it is shown, never named, and a curve whose friction falls below 0 somewhere (it would push
the cart along: the fit absorbs other physics with it) is never named.

Where the recordings cover the track, friction as a curve of the position is tried beside it
(:mod:`.track_curve`), judged on the same held-out recordings by the same rule; where both
would be named, the one that predicts them best is.

The fits are :func:`tuning.estimation.fit.fit`'s (its parameters may be vectors; the diagnosis's
batch fits scalars).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from jaxcart.effects.friction_curve import ANCHOR, KNOTS, FrictionCurve, knots
from jaxcart.errors import UserError
from jaxcart.plantspec import effect_of_param
from tuning.estimation.diagnose import track_curve
from tuning.estimation.engine import parameters
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.engine.segments import recording_name
from tuning.estimation.fit import FitSettings, fit
from tuning.estimation.fitting.names import unit_of

SIDES = ("right", "left")
#: The curve is named where its held-out sum of squares is at most this share of the named
#: structure's (its RMS at most 71 %).
HELD_OUT_SHARE = 0.5
#: An entry that departs from the slow level by less than this [N] (or fewer standard errors
#: than MIN_Z) shows no curve: friction as Coulomb and B_eq give it.
MIN_DEPARTURE, MIN_Z = 0.02, 3.0
#: The window [s] a speed is measured over: a side is fitted where the cart slid that way
#: faster than the first entry's speed.
WINDOW = 0.01


class Curve(NamedTuple):
    """The discovered curve: ``speeds`` [m/s] (0, the anchor, the entries); for each side slid,
    ``levels[side]`` the friction f_c + d [N] at each speed and ``bands[side]`` its standard
    error [N] (None where the fit held the entry: not determined); ``b_eq`` [kg/s] beside
    it."""

    speeds: tuple
    levels: dict
    bands: dict
    b_eq: float


def sides_slid(recordings) -> tuple:
    """The directions ("right", "left") the cart slid faster than the curve's first entry
    (20 mm/s), over :data:`WINDOW`, in any recording."""
    reach = knots(KNOTS)[0]
    top = {"right": 0.0, "left": 0.0}
    for rec in recordings:
        y, ts = np.asarray(rec.position, dtype=float), float(rec.sample_time)
        k = max(1, round(WINDOW / ts))
        if y.size > k:
            v = (y[k:] - y[:-k]) / (k * ts)
            top["right"], top["left"] = max(top["right"], v.max()), max(top["left"], -v.min())
    return tuple(s for s in SIDES if top[s] > reach)


def _without_replaced(values: dict) -> dict:
    """``values`` less those of the forces a curve replaces (:func:`_replaced`)."""
    return {n: v for n, v in values.items() if not _replaced(n)}


def _replaced(name: str) -> bool:
    """A force of the cart's mechanics that is not dry friction (a spring, a tilt, viscous
    friction by direction): what a search reaches for where friction's shape is missing, and
    what the curve takes the place of (the drive's, a current limit, stays)."""
    cls = effect_of_param(base_name(name))
    return (
        cls is not None
        and cls.stage == "force"
        and not cls.dry_friction
        and not parameters.is_drive(base_name(name))
    )


def structures(d, sides) -> tuple[tuple, tuple, tuple]:
    """(the named structure's parameters, the curve's, the parameters free per run) of
    diagnosis ``d``: the curve keeps the named drive, sensor and dry friction, and replaces the
    other forces (:func:`_replaced`) by f_c and the tables of the ``sides`` slid."""
    per_run = tuple(
        dict.fromkeys(n for rec in d.per_recording.values() for n in rec.get("parameters", {}))
    )
    named = tuple(dict.fromkeys([*(n for n in d.parameters if "@" not in n), *per_run]))
    kept = [n for n in named if not _replaced(n)]
    curve = tuple(dict.fromkeys([*kept, "f_c", *(f"f_curve_{s}" for s in sides)]))
    return named, curve, tuple(n for n in per_run if n in curve)


def discover(recordings, d, *, executor=None, say=None) -> dict:
    """The curves tried on ``recordings`` after diagnosis ``d`` (status "diagnosed"): of the
    speed where the cart slid faster than 20 mm/s ({"sides", "structure" (its parameters),
    "parameters" {name: {"value", "stderr", "unit"}}, "curve" (:class:`Curve` as a dict),
    "rms" [m], "named" (bool), "why" (the decision in words), "words" (what it shows)}, else
    "sides" () and "why"), and of the position where the recordings cover the track
    (:mod:`.track_curve`: the same keys but "sides" under "track", its "curve"
    :func:`.track_curve.read`'s);
    "held_out" (:func:`held_out`, both shapes' rows, or None with one recording), "plant" (the
    fitted cart of the curve named, else of the one tried: :func:`_cart`). At most one is
    named: where both predict better, the one that predicts the held-out recordings best."""
    say = say or (lambda _: None)
    sides, span = sides_slid(recordings), track_curve.covered(recordings)
    along = track_curve.fitted_knots(recordings) if span is not None else ()
    span = span if len(along) >= 2 else None  # a level that varies needs two knots
    if not sides and span is None:
        reach = track_curve.TrackFriction.covers
        return {"sides": (), "why": "the cart never slid faster than 20 mm/s nor over "
                f"{reach:g} m of the track: no curve to read"}  # fmt: skip
    named, curve, per_run = structures(d, sides)
    initial = {n: float(p["value"]) for n, p in d.parameters.items() if "@" not in n}
    # A curve starts from the named values less the forces it replaces (a value not fitted is
    # held: a spring left in would stay at its named stiffness).
    shapes = {"curve": (curve, _without_replaced(initial))} if sides else {}
    if span is not None:
        kept = [n for n in curve if effect_of_param(base_name(n)) is not FrictionCurve]
        params, held = track_curve.structure(named, kept, along, initial)
        shapes["track"] = (params, {**_without_replaced(initial), **held})
    for label, (params, _) in shapes.items():
        say(f"friction as a curve of the {_OF[label]}: {', '.join(params)}")
    joint = {}
    try:
        for label, (params, start) in {"named": (named, initial), **shapes}.items():
            joint[label] = _FIT.get(label, fit)(recordings, params, per_recording=per_run,
                                                initial=start, progress=False,
                                                executor=executor)  # fmt: skip
    except UserError as exc:  # the diagnosis stands; the curve could not be fitted
        say(f"friction curve: not fitted: {exc}")
        return {"sides": (), "why": f"the curve could not be fitted: {exc}"}
    held = held_out(recordings, {"named": named, **{k: v[0] for k, v in shapes.items()}},
                    per_run, joint, executor, say,
                    fixed={"named": initial, **{k: v[1] for k, v in shapes.items()}})  # fmt: skip
    found = {k: _shape(k, shapes[k][0], joint[k], held, sides, span) for k in shapes}
    _one_named(found, held)
    for label, shape in found.items():
        say(f"friction curve of the {_OF[label]}: {shape['why']}")
    out = found.get("curve") or {"sides": (), "why": "the cart never slid faster than 20 mm/s"}
    if "track" in found:
        out["track"] = found["track"]
    best = next((k for k in found if found[k]["named"]), next(iter(found)))
    return {**out, "held_out": held, "plant": _cart(joint[best])}


#: Each shape's variable, in words.
_OF = {"curve": "speed", "track": "position"}
#: How a shape is fitted where not by :func:`tuning.estimation.fit.fit` itself.
_FIT = {"track": track_curve.fit_tied}


def _shape(label, params, result, held, sides, span) -> dict:
    """One shape's entry of :func:`discover`: its values, what it shows, and whether the
    rule names it on its own."""
    if label == "curve":
        found = read(result, sides)
        departs, pushes = significant(result, sides), below_zero(found)
        words, curve = describe(found), found._asdict()
    else:
        curve = track_curve.read(result, span)
        departs, pushes, words = track_curve.varies(curve), (), track_curve.describe(curve)
    is_named, why = decide(held, departs, pushes, label=label)
    return {
        **({"sides": sides} if label == "curve" else {}),
        "structure": params,
        "parameters": {
            n: {"value": e.value, "stderr": e.stderr, "unit": unit_of(n)}
            for n, e in result.params.items()
            if e.identifiable
        },
        "curve": curve,
        "rms": result.rms_after_exact,
        "named": is_named,
        "why": why,
        "words": words,
    }


def _one_named(found: dict, held) -> None:
    """Where both shapes would be named, keep the one that predicts the held-out recordings
    best and say why the other is not."""
    named = [k for k, v in found.items() if v["named"]]
    if len(named) < 2:
        return
    best = min(named, key=lambda k: _share(held, k))
    for k in named:
        if k != best:
            found[k]["named"] = False
            found[k]["why"] = (
                f"not named: held out, it leaves {_share(held, k):.2f} of the named "
                f"structure's sum of squares, the curve of the {_OF[best]} "
                f"{_share(held, best):.2f}"
            )


def _cart(result):
    """The fitted cart with the curve: a driven run's plant (its drive with it), else a
    tap's."""
    plants = [s.plant for s in result.segments]
    return next((p for p in plants if p.motor_connected), plants[0] if plants else None)


def read(result, sides) -> Curve:
    """The :class:`Curve` of a fit with f_c and the curve's tables, from its fitted cart (a
    value the fit held counts at the value held): each side's friction at the anchor (f_c,
    +- f_c_asym where the cart has it) and at each entry, with standard errors (None for an
    entry the fit held: not determined by the recordings)."""
    plant = next(s.plant for s in result.segments if "f_c" in s.plant.param_names())
    have = plant.param_names()
    p = result.params

    def se(name):
        e = p.get(name)
        return (e.stderr or 0.0) if e is not None and e.identifiable else None

    asym = float(plant.get("f_c_asym")) if "f_c_asym" in have else 0.0
    se_slow = math.hypot(se("f_c") or 0.0, se("f_c_asym") or 0.0)
    levels, bands = {}, {}
    for side in sides:
        # The slow level of this side: Coulomb's, split by its asymmetry where it has one.
        slow = float(plant.get("f_c")) + (asym if side == "right" else -asym)
        table = plant.get(f"f_curve_{side}") if f"f_curve_{side}" in have else (0.0,) * KNOTS
        errors = [se(f"f_curve_{side}[{k}]") for k in range(KNOTS)]
        levels[side] = [slow, slow, *(slow + float(v) for v in table)]
        bands[side] = [se_slow, se_slow] + [
            None if e is None else math.hypot(e, se_slow) for e in errors
        ]
    return Curve((0.0, ANCHOR, *knots(KNOTS)), levels, bands, float(plant.get("B_eq")))


def significant(result, sides) -> list:
    """The entries that depart from the slow level: [(name, value [N], z)]."""
    out = []
    for side in sides:
        for k in range(KNOTS):
            e = result.params.get(f"f_curve_{side}[{k}]")
            if e is None or not e.identifiable or not e.stderr:
                continue
            z = abs(e.value) / e.stderr
            if abs(e.value) >= MIN_DEPARTURE and z >= MIN_Z:
                out.append((e.name, e.value, z))
    return out


def held_out(recordings, structures, per_run, joint, executor=None, say=None, fixed=None):
    """Each recording left out in turn: each structure ({label: parameters}, "named" among
    them) fitted to the others from its joint fit's values (``joint`` {label: FitResult};
    ``fixed`` {label: {name: value}}: values a structure holds, as its joint fit did), then
    predicting it, its own drive values and start state fitted to it. A structure predicts a
    recording only where the others determine every value its joint fit did (else None
    there); a recording counts where the named structure and some other predict it.
    {"recordings": names, "samples": each one's, label: RMS [m] each (or None),
    "named_sse" [m^2]; for each other label, over the recordings it predicts: f"{label}_sse",
    f"{label}_named_sse" (the named structure's there) [m^2], f"{label}_count"}, or None with
    one recording."""
    if len(recordings) < 2:
        return None
    rows = {"recordings": [], "samples": [], **{label: [] for label in structures}}
    for i, rec in enumerate(recordings):
        others = [r for j, r in enumerate(recordings) if j != i]
        rms = {
            label: _predicted(rec, others, params, per_run, joint[label],
                              (fixed or {}).get(label, {}), executor, _FIT.get(label, fit))
            for label, params in structures.items()
        }  # fmt: skip
        if rms["named"] is None or all(v is None for v in rms.values()):
            if say:
                say(f"  {recording_name(rec)}: not held out (the others do not determine it)")
            continue
        rows["recordings"].append(recording_name(rec))
        rows["samples"].append(int(np.asarray(rec.position).size))
        for label, value in rms.items():
            rows[label].append(value)
        if say:
            say(f"  {recording_name(rec)} held out: " + ", ".join(
                f"{label} {'-' if v is None else f'{v * 1e3:.4f}'} mm"
                for label, v in rms.items()))  # fmt: skip
    n = rows["samples"]
    rows["named_sse"] = float(sum(k * v**2 for k, v in zip(n, rows["named"], strict=True)))
    for label in structures:
        if label != "named":
            use = [j for j, v in enumerate(rows[label]) if v is not None]
            rows[f"{label}_sse"] = float(sum(n[j] * rows[label][j] ** 2 for j in use))
            rows[f"{label}_named_sse"] = float(sum(n[j] * rows["named"][j] ** 2 for j in use))
            rows[f"{label}_count"] = len(use)
    return rows


def _predicted(rec, others, params, per_run, joint, fixed, executor, fitter) -> float | None:
    """The RMS [m] of recording ``rec`` predicted by the structure ``params`` fitted to
    ``others`` (by ``fitter``) from its ``joint`` fit's values, or None where the others do not
    determine every value that the joint fit did."""
    own = [n for n in per_run if rec.kind != "tap" or not parameters.is_drive(n)]
    start = {**fixed, **shared_values(joint, params)}
    # From the joint fit's values, near the fold's own: the continuation that leads a fit from
    # a poor start is not needed (FitSettings.warm).
    warm = FitSettings.warm()
    try:
        rest = fitter(others, params, per_recording=per_run, initial=start, progress=False,
                   executor=executor, settings=warm)  # fmt: skip
    except UserError:  # a value only this recording drives
        return None
    # (Shared values: a run's own, name@k, is numbered anew among the others.)
    known = {n for n, e in joint.params.items() if e.identifiable and "@" not in n}
    if any(not e.identifiable for n, e in rest.params.items() if n in known):
        return None  # the others leave a value this recording alone determines
    pred = fit([rec], own, initial={**start, **shared_values(rest, params)}, progress=False,
               executor=executor, settings=warm)  # fmt: skip
    value = pred.rms_after_exact
    return float(value) if value is not None and np.isfinite(value) else None


def shared_values(result, params) -> dict:
    """{base name: value} of ``params`` (vectors as tuples) from a fit's cart: every shared
    value, from the first segment that has it."""
    out = {}
    for name in params:
        base = base_name(name)
        for seg in result.segments:
            if base in seg.plant.param_names():
                v = seg.plant.get(base)
                out[base] = tuple(float(x) for x in v) if isinstance(v, tuple) else float(v)
                break
    return out


def below_zero(c: Curve) -> list:
    """Where the curve's friction falls below 0 (it would push the cart along): [(side, speed
    [m/s], level [N])]. A fit puts it there only to absorb some other physics."""
    return [
        (side, q, v)
        for side, levels in c.levels.items()
        for q, v, b in zip(c.speeds, levels, c.bands[side], strict=True)
        if b is not None and v < 0
    ]


def decide(held, departs, pushes=(), label="curve") -> tuple[bool, str]:
    """(named, why): the rule of the module's docstring, in words, for the shape ``label`` of
    ``held`` ("curve", the speed's; "track", the position's); ``pushes`` (:func:`below_zero`):
    a friction that pushes is never named."""
    if pushes:
        side, q, v = pushes[0]
        return False, (
            f"not named: its friction falls below 0 ({v:.2f} N moving {side} at "
            f"{q * 1e3:.0f} mm/s), which no friction does: it absorbs other physics"
        )
    if not departs:
        return False, (
            "no entry departs from the slow level (Coulomb and B_eq hold)"
            if label == "curve"
            else "the friction does not vary along the track (one level holds)"
        )
    if held is None or not held.get(f"{label}_count"):
        return False, "shown, not named: no recording could be held out to judge it"
    share = _share(held, label)
    verdict = "named" if share <= HELD_OUT_SHARE else "not named"
    return share <= HELD_OUT_SHARE, (
        f"{verdict}: held out, it leaves {share:.2f} of the named structure's sum of squares "
        f"over {held[f'{label}_count']} recording(s) (named under {HELD_OUT_SHARE:g})"
    )


def _share(held, label: str) -> float:
    """The shape's held-out sum of squares as a share of the named structure's, over the
    recordings it predicts."""
    named = held[f"{label}_named_sse"]
    return held[f"{label}_sse"] / named if named > 0 else math.inf


def describe(c: Curve) -> str:
    """What the curve shows, one sentence per side and one comparing them."""
    parts, tops = [], {}
    for side, lv in c.levels.items():
        bands = c.bands[side]
        known = [
            (q, v) for q, v, b in zip(c.speeds[1:], lv[1:], bands[1:], strict=True) if b is not None
        ]
        if len(known) < 2:
            continue
        (q0, v0), (q1, v1) = known[0], known[-1]
        tops[side] = v1
        way = "rises" if v1 > v0 else "falls"
        parts.append(
            f"moving {side}, friction {way} from {v0:.2f} N at {q0 * 1e3:.0f} mm/s to "
            f"{v1:.2f} N at {q1 * 1e2:.0f} cm/s (beside viscous B_eq {c.b_eq:.3g} kg/s)"
        )
    if len(tops) == 2 and min(tops.values()) > 0:
        r, l_ = tops["right"], tops["left"]
        more = "right" if r > l_ else "left"
        parts.append(f"{abs(r - l_) / min(r, l_) * 100:.0f} % higher moving {more} at speed")
    return "; ".join(parts) if parts else "the curve is not determined by these recordings"
