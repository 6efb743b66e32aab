"""The tuner's result: :class:`TuneResult` and its JSON, made from where the iteration ended
and the exact re-check of its candidates (:func:`conclude`)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from hw.control_law import PID, float_pid
from jaxcart.metrics import StepInfo
from jaxcart.params import Plant
from tuning.design.candidates import failing_constraints, verify, worst
from tuning.design.iteration import Descent, smooth_metrics
from tuning.design.limits import binding_text
from tuning.design.losses import GAIN_NAMES, PARAM_NAMES, Spec, controller_with, params_of
from tuning.design.problem import TuningProblem
from tuning.design.wording import bound_note, verdict


@dataclass
class TuneResult:
    """Outcome of :func:`tuning.design.tune.tune`.

    gains: the tuned controller (every setting); exact / smooth: its metrics on the nominal
    plant from the exact simulator and from the smooth one at the final widths; meets: the
    specification is met on the exact simulator (for robust tuning: on every plant of the
    check set); failing: names of the constraints that fail ("settling_time", "overshoot");
    message: one line saying what happened; history: one dict per iteration (iteration,
    seconds, scale, loss, settling_time [s] and overshoot [%] surrogates of the best start,
    best_settling_time [s] feasible so far on the hard-clip loop); seconds: wall time of the
    call [s] (compilation included); seconds_to_spec: wall time until gains that meet the
    specification were first found [s] (None if never); worst: robust tuning's worst case over
    the check set (exact simulator): a StepInfo whose fields are each the worst over the set;
    plant_set: per plant checked, its parameters and exact metrics; free: the tuned
    parameters; bounds: their search box {name: (lo, hi)}; on_bound: {name: (side, bound)} for
    each free parameter on or within 1 % of a bound (:func:`on_bounds`); limits: the upper ends
    of the box derived from the cart ({name: :class:`tuning.design.limits.Limit`}).
    """

    gains: PID
    exact: StepInfo
    smooth: StepInfo
    meets: bool
    failing: tuple[str, ...]
    message: str
    spec: Spec
    plant: Plant
    history: list = field(default_factory=list)
    seconds: float = 0.0
    seconds_to_spec: float | None = None
    iterations: int = 0
    n_starts: int = 1
    worst: StepInfo | None = None
    plant_set: list | None = None
    free: tuple[str, ...] = GAIN_NAMES
    bounds: dict = field(default_factory=dict)
    on_bound: dict = field(default_factory=dict)
    limits: dict = field(default_factory=dict)

    @property
    def binding(self) -> str:
        """Which limit derived from the cart sets the design, or that none does (a sentence,
        :func:`tuning.design.limits.binding_text`)."""
        return binding_text(self.gains, {n: v for n, v in self.limits.items() if n in self.free})

    def bound_note(self, widen: str | None = None) -> str | None:
        """One line naming every free parameter on (or within 1 % of) a bound of the search
        box that is not a limit of the cart (:attr:`binding` says those), and how to widen it
        (``widen``: the way to say it, default the ``bounds=`` argument of
        :func:`tuning.design.tune.tune`); None when there is none."""
        arbitrary = {
            n: v for n, v in self.on_bound.items() if not (n in self.limits and v[0] == "upper")
        }
        return bound_note(self.gains, arbitrary, self.bounds, widen)

    def to_json(self) -> dict:
        """The ``--json`` document: gains, exact and smooth metrics, wall time [s], ..."""
        keys = ("settling_time", "overshoot", "rise_time", "steady_state_error")
        doc = {
            "gains": self.gains.to_dict(),
            "exact": {k: json_number(getattr(self.exact, k)) for k in keys},
            "smooth": {k: json_number(getattr(self.smooth, k)) for k in keys},
            "seconds": self.seconds,
            "seconds_to_spec": self.seconds_to_spec,
            "meets": self.meets,
            "failing": list(self.failing),
            "message": self.message,
            "spec": dataclasses.asdict(self.spec),
            "iterations": self.iterations,
            "starts": self.n_starts,
            "free": list(self.free),
            "bounds": {n: list(b) for n, b in self.bounds.items()},
            "on_bound": {
                n: {"side": side, "bound": b, "value": float(getattr(self.gains, n))}
                for n, (side, b) in self.on_bound.items()
            },
            "bound_note": self.bound_note(),
            "limits": {
                n: {"bound": lim.bound, "what": lim.what, "why": lim.why}
                for n, lim in self.limits.items()
                if n in self.free
            },
            "binding": self.binding,
        }
        doc["gains"]["v_limit"] = json_number(doc["gains"]["v_limit"])
        if self.worst is not None:
            doc["worst"] = {k: json_number(getattr(self.worst, k)) for k in keys}
            doc["plant_set"] = self.plant_set
        return doc


def json_number(x):
    """``x`` as a float, or the text "inf", "-inf", "nan" (JSON has no such numbers)."""
    x = float(x)
    return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")


def info_dict(info: StepInfo) -> dict:
    """A StepInfo as JSON values."""
    return {k: (bool(v) if k == "diverged" else json_number(v)) for k, v in info._asdict().items()}


def on_bounds(values: Mapping, free: Sequence[str], bounds: Mapping, rel: float = 0.01) -> dict:
    """The free parameters that sit on, or within ``rel`` (1 %) of, a bound: {name: (side,
    bound)} with side "upper" or "lower". Such a result is the box's answer, not the problem's:
    widening that bound may improve it."""
    out = {}
    for name in free:
        lo, hi = bounds[name]
        v = float(values[name])
        if v >= hi * (1 - rel):
            out[name] = ("upper", float(hi))
        elif v <= lo * (1 + rel):
            out[name] = ("lower", float(lo))
    return out


def conclude(p: TuningProblem, update, descent: Descent, n_starts: int, t0: float) -> TuneResult:
    """The best candidates checked on the exact simulator, and the :class:`TuneResult`."""
    chosen, exact, checked = verify(
        descent.candidates.found, p.template, p.plant, p.experiment, p.spec, p.check_plants
    )
    gains = float_pid(controller_with(float_pid(p.template), [float(x) for x in chosen]))
    smooth = smooth_metrics(update, p, descent, gains)
    worst_info = plant_set = None
    judged = exact
    if p.robust:
        worst_info = judged = worst(checked)
        plant_set = [
            {"params": v, "exact": info_dict(i)}
            for v, i in zip(p.check_values, checked, strict=True)
        ]
    failing = failing_constraints(judged, p.spec)
    meets = not failing
    seconds_to_spec = descent.candidates.seconds_to_spec
    if meets and seconds_to_spec is None:
        seconds_to_spec = time.perf_counter() - t0
    values = dict(zip(PARAM_NAMES, params_of(gains), strict=True))
    return TuneResult(
        gains=gains,
        exact=exact,
        smooth=smooth,
        meets=meets,
        failing=failing,
        message=verdict(meets, failing, judged, p.spec, p.robust, len(p.check_plants or [])),
        spec=p.spec,
        plant=p.plant,
        history=descent.history,
        seconds=time.perf_counter() - t0,
        seconds_to_spec=seconds_to_spec if meets else None,
        iterations=descent.iterations,
        n_starts=n_starts,
        worst=worst_info,
        plant_set=plant_set,
        free=p.free,
        bounds={n: p.box[n] for n in p.free},
        on_bound=on_bounds(values, p.free, p.box),
        limits=p.limits,
    )
