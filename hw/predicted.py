"""A run against its prediction (numpy and the standard library only: the lab PC runs it).

A design handed to the cart carries its prediction (``jaxcart lab`` and ``jaxcart tune`` write
it into the gains file, :meth:`tuning.design.prediction.Prediction.to_json`): for each metric
the fitted cart's value and a band that a run lies in with the band's probability, and each
fitted value's standard error with the metrics' change per standard error. :func:`check_run`
compares a run's metrics with it; where one falls outside its band, it says which single
fitted value, moved by how many of its standard errors, would explain the difference (the
change needed over the metric's change per standard error, the fewest first): a run that
settles 80 ms late where the drive's limit moves the settling time by -55 ms per standard
error is explained by a limit 1.5 standard errors lower. Where every value would have to move
by more than :data:`FAR` standard errors, the difference is something the model leaves out. A
drive value the prediction draws from Student's t over a few runs (its sensitivity's "dof")
is judged in the t's scale, as far as the t reaches as often (:data:`FAR_T`): from two runs a
new run's drive may lie much further out than a fitted value's three standard errors.

>>> prediction = {"level": 0.9, "step": 0.5, "metrics": {"settling_time": {"nominal": 0.8,
...     "band": [0.75, 0.85]}}, "sensitivity": {"v_sat": {"stderr": 0.3, "value": 5.5,
...     "unit": "V", "settling_time": -0.05}}}
>>> check = check_run({"settling_time": 0.9}, prediction)
>>> check["inside"], check["outside"][0]["explained_by"][0]["name"]
(False, 'v_sat')
"""

from __future__ import annotations

import math

#: The metrics a run is checked on, with their units and how they are written.
CHECKED = {"settling_time": ("s", 1.0, "settled"), "overshoot": ("%", 1.0, "overshot")}
#: A value that would have to move further than this many standard errors does not explain a
#: difference.
FAR = 3.0
#: The same for a drive value drawn from Student's t with 1, 2, ... 30 degrees of freedom, in
#: the t's scale: its two-sided 0.27 % point, as FAR is the normal's (scipy.stats.t.ppf(0.99865,
#: dof); more degrees of freedom: FAR).
FAR_T = (
    235.78, 19.21, 9.22, 6.62, 5.51, 4.90, 4.53, 4.28, 4.09, 3.96, 3.85, 3.76, 3.69, 3.64, 3.59,
    3.54, 3.51, 3.48, 3.45, 3.42, 3.40, 3.38, 3.36, 3.34, 3.33, 3.32, 3.30, 3.29, 3.28, 3.27,
)  # fmt: skip


def far(entry: dict) -> float:
    """How far (in its standard errors, or its t's scale) a value of a prediction's
    sensitivity ``entry`` may move and still explain a difference."""
    try:
        dof = int(_number(entry.get("dof")))
    except (TypeError, ValueError, OverflowError):  # none, or not a number: a fitted value
        return FAR
    return FAR_T[dof - 1] if 1 <= dof <= len(FAR_T) else FAR


def _number(x) -> float:
    """A number of a gains file (non-finite ones are written as text)."""
    if isinstance(x, str):
        return float(x)
    return float(x) if x is not None else math.nan


def problem_of(prediction) -> tuple[str, str] | None:
    """(field, what is wrong) of a gains file's prediction that :func:`check_run` cannot
    read (a band edited by hand: reversed, or written as text), or None."""
    if not isinstance(prediction, dict) or not isinstance(prediction.get("metrics", {}), dict):
        return "prediction", "expected an object with a metrics object"
    for name, pred in prediction.get("metrics", {}).items():
        if name not in CHECKED or pred is None:
            continue
        where = f"prediction.metrics.{name}"
        band = pred.get("band") if isinstance(pred, dict) else None
        try:
            lo, hi = (_number(x) for x in band)
            nominal = _number(pred["nominal"])
        except (TypeError, ValueError, KeyError):
            return where, f"band {band!r}: give [low, high] as two numbers, and a nominal"
        if math.isnan(lo) or math.isnan(hi) or math.isnan(nominal) or not lo <= hi:
            return where, f"band [{lo:g}, {hi:g}]: give [low, high] with low <= high"
    return None


def check_run(measured: dict, prediction: dict) -> dict:
    """The run's ``measured`` metrics ({name: value}: settling_time [s], overshoot [%])
    against ``prediction`` (the gains file's): {"inside": every checked metric within its band,
    "level", "metrics": [{"name", "measured", "nominal", "band", "inside"}], "outside": those
    outside, each with "explained_by": [{"name", "sigmas", "value", "unit", "stderr", "far"}]
    (the fitted values that explain it within :func:`far` standard errors, the likeliest
    first)}."""
    rows = []
    for name in CHECKED:
        pred = prediction.get("metrics", {}).get(name)
        if pred is None or name not in measured:
            continue
        lo, hi = (_number(x) for x in pred["band"])
        value = _number(measured[name])
        row = {
            "name": name,
            "measured": value,
            "nominal": _number(pred["nominal"]),
            "band": (lo, hi),
            "inside": bool(lo <= value <= hi),
        }
        if not row["inside"]:
            row["explained_by"] = _explained_by(name, value - row["nominal"], prediction)
        rows.append(row)
    return {
        "inside": all(r["inside"] for r in rows),
        "level": _number(prediction.get("level", math.nan)),
        "metrics": rows,
        "outside": [r for r in rows if not r["inside"]],
    }


def _explained_by(metric: str, difference: float, prediction: dict) -> list[dict]:
    """The fitted values that would move ``metric`` by ``difference`` within :func:`far` of
    their standard errors (a drive value's: its t's scale), the likeliest first."""
    out = []
    if not math.isfinite(difference):
        return out
    for name, s in prediction.get("sensitivity", {}).items():
        per_sigma = _number(s.get(metric))
        if not math.isfinite(per_sigma) or per_sigma == 0:
            continue  # (a value the metric does not move with)
        sigmas = difference / per_sigma
        value, se = _number(s.get("value")), _number(s.get("stderr"))
        # a drive value (a limit, a gain) moved through zero explains nothing
        if abs(sigmas) <= far(s) and not ("dof" in s and (value + sigmas * se) * value <= 0):
            out.append(
                {
                    "name": name,
                    "sigmas": sigmas,
                    "value": value,
                    "stderr": se,
                    "unit": s.get("unit", ""),
                    "far": far(s),
                }
            )
    # the likeliest first: the fewest standard errors, each as a share of how far it may go
    return sorted(out, key=lambda e: abs(e["sigmas"]) / e["far"])


def _fmt(name: str, x: float) -> str:
    unit = CHECKED[name][0]
    if not math.isfinite(x):
        return "never" if name == "settling_time" else "inf"
    return f"{x:.3f} s" if unit == "s" else f"{x:.2f} %"


def check_lines(check: dict) -> list[str]:
    """The check in words, one line each."""
    level = check["level"]
    lines = []
    for row in check["metrics"]:
        lo, hi = row["band"]
        where = "inside" if row["inside"] else "OUTSIDE"
        lines.append(
            f"{row['name'].replace('_', ' ')} {_fmt(row['name'], row['measured'])}: {where} the "
            f"predicted {level:.0%} band {_fmt(row['name'], lo)} - {_fmt(row['name'], hi)} "
            f"(the fitted cart: {_fmt(row['name'], row['nominal'])})"
        )
    for row in check["outside"]:
        lines.append(_explanation(row))
    return lines


def _explanation(row: dict) -> str:
    """Which fitted value would explain a metric outside its band, in words."""
    name = row["name"].replace("_", " ")
    ways = row.get("explained_by", [])
    if not ways:
        return (
            f"no single fitted value explains the {name} within {FAR:g} standard errors (a "
            "drive value: as far as its runs' spread reaches as often): the run shows "
            "something the model of the cart leaves out (jaxcart diagnose with this run among "
            "the recordings)"
        )
    parts = []
    for e in ways[:3]:
        side = "higher" if e["sigmas"] > 0 else "lower"
        moved = e["value"] + e["sigmas"] * e["stderr"]
        what = "standard errors" if e["far"] == FAR else "times its runs' spread"
        parts.append(
            f"{e['name']} {abs(e['sigmas']):.1f} {what} {side} ({moved:.4g} "
            f"{e['unit']} for {e['value']:.4g})".replace(" )", ")")
        )
    return f"the {name} would be explained by " + ", or ".join(parts)
