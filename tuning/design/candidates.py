"""The tuner's candidates and their exact re-check.

Every iteration's smooth runs also give the step metrics at the exact thresholds
(:class:`Candidates` keeps them, rounded, with the best so far); at the end the leading
candidates run on the exact simulator (:func:`verify`), whose best wins.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hw.control_law import PID, float_pid
from jaxcart.exact import step_info_exact
from jaxcart.metrics import StepInfo
from jaxcart.params import Plant
from tuning.design.losses import Spec, controller_with


def exact_info(plant: Plant, controller: PID, experiment) -> StepInfo:
    """Metrics of one run on the exact simulator (:mod:`jaxcart.exact`)."""
    return step_info_exact(plant, float_pid(controller), experiment)


def violation(settling, overshoot, spec: Spec) -> float:
    """How far from the specification: max of the normalized metrics (< 1 meets it)."""
    settling = min(float(settling), 10.0 * spec.horizon)
    overshoot = min(float(overshoot), 1e4)
    return max(settling / spec.settling_time, overshoot / spec.overshoot)


def failing_constraints(info: StepInfo, spec: Spec) -> tuple[str, ...]:
    """Names of the constraints ``info`` fails: "settling_time", "overshoot", "diverged"."""
    out = []
    if bool(info.diverged):
        out.append("diverged")
    if not float(info.settling_time) < spec.settling_time:
        out.append("settling_time")
    if not float(info.overshoot) < spec.overshoot:
        out.append("overshoot")
    return tuple(out)


def worst(infos: Sequence[StepInfo]) -> StepInfo:
    """Field-wise worst of several StepInfos (max of every metric, any diverged)."""
    arr = {k: [getattr(i, k) for i in infos] for k in StepInfo._fields}
    return StepInfo(
        **{k: (any(v) if k == "diverged" else float(np.max(v))) for k, v in arr.items()}
    )


@dataclass
class Candidates:
    """The step metrics (exact thresholds) of every start's smooth run: the candidates for
    the exact check and the best point so far.

    found: rounded params -> (key, params, settling [s], overshoot [%], scale); key: the
    best (settling, overshoot), or (inf, violation) while nothing meets the specification;
    improved_at: the last iteration the settling time improved by half a sample or more;
    seconds_to_spec: when a point first met the specification [s]."""

    spec: Spec
    t0: float
    found: dict = field(default_factory=dict)
    key: tuple = (math.inf, math.inf)
    improved_at: int | None = None
    seconds_to_spec: float | None = None

    def record(self, params, metrics, it: int, scale: float, ts: float) -> None:
        spec = self.spec
        settle, over = np.asarray(metrics.settling_time), np.asarray(metrics.overshoot)
        bad = np.asarray(metrics.diverged)
        for g, s, o, b in zip(np.asarray(params), settle, over, bad, strict=True):
            feasible = (not b) and s < spec.settling_time and o < spec.overshoot
            key = (s, o) if feasible else (math.inf, violation(s, o, spec))
            # The finest widths rank first among equals: they are closest to the exact loop.
            self.found[tuple(float(f"{x:.5g}") for x in g)] = (key, g, s, o, scale)
            if key < self.key:
                # Progress is half a sample or more of settling time (or the first feasible).
                if feasible and key[0] < self.key[0] - 0.5 * ts:
                    self.improved_at = it
                if feasible and self.seconds_to_spec is None:
                    self.seconds_to_spec = time.perf_counter() - self.t0
                self.key = key


def verify(candidates, template, plant, experiment, spec, check_plants, tries=None):
    """Best of the leading candidates on the exact simulator; else the one closest to spec.

    The candidates were ranked by the smooth runs, which differ a little from the exact loop
    (most at wide smoothing), so the leading ``tries`` (default 6 for one plant, 3 for a set)
    are all checked and the best exact result wins. Returns (parameters, exact StepInfo on
    ``plant``, per-plant exact StepInfos or None).
    """
    tries = tries or (6 if check_plants is None else 3)
    ranked = sorted(candidates.values(), key=lambda c: (c[0], c[4]))
    best = None
    for _key, g, _s, _o, _scale in ranked[:tries]:
        pid = controller_with(float_pid(template), [float(x) for x in g])
        if check_plants is None:
            info = exact_info(plant, pid, experiment)
            judged, per_plant = info, None
        else:
            per_plant = [exact_info(p, pid, experiment) for p in check_plants]
            judged = worst(per_plant)
            info = exact_info(plant, pid, experiment)
        ok = not failing_constraints(judged, spec)
        score = (
            0 if ok else 1,
            float(judged.settling_time) if ok else 0.0,
            violation(judged.settling_time, judged.overshoot, spec),
        )
        if best is None or score < best[0]:
            best = (score, g, info, per_plant)
    _, g, info, per_plant = best
    return g, info, per_plant
