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

The fits are :func:`tuning.estimation.fit.fit`'s (its parameters may be vectors; the diagnosis's
batch fits scalars).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from jaxcart.effects.friction_curve import ANCHOR, KNOTS, knots
from jaxcart.errors import UserError
from jaxcart.plantspec import effect_of_param
from tuning.estimation.engine import parameters
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.engine.segments import recording_name
from tuning.estimation.fit import fit
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
    """The curve tried on ``recordings`` after diagnosis ``d`` (status "diagnosed"): {"sides",
    "structure" (the curve's parameters), "parameters" {name: {"value", "stderr", "unit"}},
    "curve" (:class:`Curve` as a dict), "rms" [m], "held_out" (:func:`held_out`, or None with
    one recording), "named" (bool), "why" (the decision in words), "words" (what the curve
    shows), "plant" (the fitted cart with the curve, :func:`_cart`)}, or {"sides": (), "why"}
    where the cart never slid fast enough or the curve could not be fitted."""
    say = say or (lambda _: None)
    sides = sides_slid(recordings)
    if not sides:
        return {"sides": (), "why": "the cart never slid faster than 20 mm/s: no curve to read"}
    named, curve, per_run = structures(d, sides)
    initial = {n: float(p["value"]) for n, p in d.parameters.items() if "@" not in n}
    say(f"friction as a curve of the speed ({', '.join(sides)}): {', '.join(curve)}")
    joint = {}
    try:
        for label, params in (("named", named), ("curve", curve)):
            joint[label] = fit(recordings, params, per_recording=per_run, initial=initial,
                               progress=False, executor=executor)  # fmt: skip
    except UserError as exc:  # the diagnosis stands; the curve could not be fitted
        say(f"friction curve: not fitted: {exc}")
        return {"sides": (), "why": f"the curve could not be fitted: {exc}"}
    result = joint["curve"]
    found = read(result, sides)
    held = held_out(recordings, {"named": named, "curve": curve}, per_run, joint, executor, say)
    is_named, why = decide(held, significant(result, sides), below_zero(found))
    say(f"friction curve: {why}")
    return {
        "sides": sides,
        "structure": curve,
        "parameters": {
            n: {"value": e.value, "stderr": e.stderr, "unit": unit_of(n)}
            for n, e in result.params.items()
            if e.identifiable
        },
        "curve": found._asdict(),
        "rms": result.rms_after_exact,
        "held_out": held,
        "named": is_named,
        "why": why,
        "words": describe(found),
        "plant": _cart(result),
    }


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


def held_out(recordings, structures, per_run, joint, executor=None, say=None) -> dict | None:
    """Each recording left out in turn: each structure ({label: parameters}) fitted to the
    others from its joint fit's values (``joint`` {label: FitResult}), then predicting it, its
    own drive values and start state fitted to it. A recording counts only where the others
    determine every value of both structures that the joint fit did. {"recordings": names,
    label: RMS [m] each, "samples": each one's, f"{label}_sse" [m^2]}, or None with one
    recording."""
    if len(recordings) < 2:
        return None
    rows = {"recordings": [], "samples": [], **{label: [] for label in structures}}
    for i, rec in enumerate(recordings):
        others = [r for j, r in enumerate(recordings) if j != i]
        own = [n for n in per_run if rec.kind != "tap" or not parameters.is_drive(n)]
        rms = {}
        for label, params in structures.items():
            start = shared_values(joint[label], params)
            try:
                rest = fit(others, params, per_recording=per_run, initial=start,
                           progress=False, executor=executor)  # fmt: skip
            except UserError:  # a value only this recording drives
                break
            # (Shared values: a run's own, name@k, is numbered anew among the others.)
            known = {n for n, e in joint[label].params.items() if e.identifiable and "@" not in n}
            if any(not e.identifiable for n, e in rest.params.items() if n in known):
                break  # the others leave a value this recording alone determines
            pred = fit([rec], own, initial={**start, **shared_values(rest, params)},
                       progress=False, executor=executor)  # fmt: skip
            rms[label] = pred.rms_after_exact
        if len(rms) < len(structures) or not all(np.isfinite(list(rms.values()))):
            if say:
                say(f"  {recording_name(rec)}: not held out (the others do not determine it)")
            continue
        rows["recordings"].append(recording_name(rec))
        rows["samples"].append(int(np.asarray(rec.position).size))
        for label, value in rms.items():
            rows[label].append(float(value))
        if say:
            say(f"  {recording_name(rec)} held out: " + ", ".join(
                f"{label} {value * 1e3:.4f} mm" for label, value in rms.items()))  # fmt: skip
    n = np.asarray(rows["samples"], dtype=float)
    for label in structures:
        rows[f"{label}_sse"] = float(np.sum(n * np.asarray(rows[label]) ** 2))
    return rows


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


def decide(held, departs, pushes=()) -> tuple[bool, str]:
    """(named, why): the rule of the module's docstring, in words; ``pushes``
    (:func:`below_zero`): a friction that pushes is never named."""
    if pushes:
        side, q, v = pushes[0]
        return False, (
            f"not named: its friction falls below 0 ({v:.2f} N moving {side} at "
            f"{q * 1e3:.0f} mm/s), which no friction does: it absorbs other physics"
        )
    if not departs:
        return False, "no entry departs from the slow level (Coulomb and B_eq hold)"
    if held is None or not held["recordings"]:
        return False, "shown, not named: no recording could be held out to judge it"
    share = held["curve_sse"] / held["named_sse"] if held["named_sse"] > 0 else math.inf
    verdict = "named" if share <= HELD_OUT_SHARE else "not named"
    return share <= HELD_OUT_SHARE, (
        f"{verdict}: held out, it leaves {share:.2f} of the named structure's sum of squares "
        f"over {len(held['recordings'])} recording(s) (named under {HELD_OUT_SHARE:g})"
    )


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
