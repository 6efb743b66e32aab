"""A diagnosis's chosen structure as a :class:`tuning.estimation.fit.FitResult`.

A joint diagnosis ends with the cart fitted: its chosen structure re-fitted on the exact
simulator over every recording, shared values with standard errors and each run's own. A
command that wants the cart (``jaxcart lab``'s joint section, its plant file, the re-tune)
takes it from here instead of fitting the recordings again.
"""

from __future__ import annotations

import numpy as np

from tuning.estimation.engine.noise import effective_samples
from tuning.estimation.fit import Estimate, FitResult, SegmentFit, plant_values


def fit_result(d) -> FitResult:
    """The :class:`FitResult` of :class:`~.result.Diagnosis` ``d`` (status "diagnosed"): its
    shared values and each recording's own (``v_sat@2``) with standard errors, each
    recording's exact runs before (the handout's model, B_eq fitted) and after and the values
    of the fit that left it out (:attr:`SegmentFit.held_out`), and the fitted cart (effects
    included) as :attr:`FitResult.cart`."""
    if d.status != "diagnosed":
        raise ValueError(f"the diagnosis has no fit (status {d.status!r})")
    params = {n: _estimate(n, p) for n, p in d.parameters.items() if p.get("value") is not None}
    segments = []
    folds = d.cross_validation.get("folds") or [{}] * len(d.traces)
    for k, (rec, trace, fold) in enumerate(
        zip(d.per_recording.values(), d.traces, folds, strict=True)
    ):
        # A drive limit above what its run drove is not determined there: not a run's value.
        params.update(
            {
                f"{n}@{k}": _estimate(f"{n}@{k}", p)
                for n, p in rec["parameters"].items()
                if p.get("acts", True)
            }
        )
        measured = np.asarray(trace["measured"])
        before, after = np.asarray(trace["baseline"]), np.asarray(trace["after"])
        segments.append(
            SegmentFit(
                trace["name"],
                rec["kind"],
                np.asarray(trace["time"]),
                measured,
                before,
                after,
                before,
                after,
                {},
                d.plant,
                fold.get("values"),
            )  # fmt: skip
        )
    return FitResult(
        params=params,
        values=plant_values(d.plant, [n for n in params if "@" not in n]),
        segments=segments,
        correlation={},
        n_data=sum(s.measured.size for s in segments),
        seconds=d.seconds,
        smoothing=None,
        exact_polish=True,
        noise_floor=d.floor,
        n_effective=effective_samples([s.after_exact - s.measured for s in segments]),
        misfit=d.misfit,
        cart=d.plant,
    )


def _estimate(name: str, p: dict) -> Estimate:
    se = p.get("stderr")
    return Estimate(name, float(p["value"]), None if se is None else float(se))
