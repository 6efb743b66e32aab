"""Part (v) on the cart as measured: every design the lab has, predicted with its band, its
margins and its chance of meeting the spec, and the measured run against its prediction.

The designs: the pre-lab's (tuned on the handout's model), the one tuned for the cart as
measured (:func:`tuning.lab.cart.retune`), and the recording's own where Part (v)'s recording
ran other gains (the real recordings' PD run). Each is predicted on the cart fitted from every
recording (:func:`tuning.design.prediction.predict`: carts drawn from the fit's uncertainty and
the drive's run-to-run spread, the exact simulator), its margins taken on the fitted cart
(:func:`tuning.design.margins.margins`); the design that ran is predicted on the recording's
own experiment, and the run is checked against that prediction (:func:`hw.predicted.check_run`:
inside its band, or which fitted value would explain the difference).

:func:`compute` returns :class:`Designs`; :func:`tuning.lab.part_v_render.render_designs` writes
the subsection.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

import jaxcart as jc
from hw.predicted import check_run
from tuning.design.calibration import is_step, model_error, step_miss
from tuning.design.margins import Margins, margins
from tuning.design.prediction import Prediction, predict
from tuning.lab.context import V_SAT, value
from tuning.lab.part_v import same_gains

#: The designs' keys and how the report names them.
LABELS = {
    "prelab": "pre-lab design (handout's model)",
    "retuned": "tuned for the cart as measured",
    "recording": "the recording's gains",
}


@dataclass(frozen=True, eq=False)
class Design:
    """One design on the cart as measured: key (of :data:`LABELS`), controller, prediction,
    margins; where it ran in Part (v)'s recording, measured (the run's metrics, a
    :class:`jaxcart.metrics.StepInfo`), run ((time [s], position [m])) and check (the run
    against the prediction, :func:`hw.predicted.check_run`)."""

    key: str
    controller: object
    prediction: Prediction
    margins: Margins
    measured: object = None
    run: tuple | None = None
    check: dict | None = None

    @property
    def label(self) -> str:
        return LABELS[self.key]


@dataclass(frozen=True, eq=False)
class Designs:
    """Part (v)'s designs (:class:`Design`, in :data:`LABELS`' order), the recording's name
    (or None), where the cart's fit comes from, and how far the fitted cart misses each
    recorded step (:class:`tuning.design.calibration.StepMiss`; the bound on a new run's miss widens
    every band: ``model_error``) and the driven runs each drive value is drawn from ({name: n})."""

    designs: tuple
    recording: str | None
    source: str
    misses: tuple = ()
    model_error: dict = dataclasses.field(default_factory=dict)
    drive_runs: dict = dataclasses.field(default_factory=dict)

    def get(self, key: str) -> Design | None:
        return next((d for d in self.designs if d.key == key), None)


def compute(
    rec, joint, prelab_gains, recordings=(), *, executor=None, say=lambda t: None
) -> Designs | None:
    """The designs of Part (v) on ``joint`` (:class:`tuning.lab.cart.JointCart` with its
    design; None without one: no driven recording); ``rec``: Part (v)'s recording or None;
    ``prelab_gains``: the pre-lab's PID; ``recordings``: every recording of the lab (its
    closed-loop steps say how far the model misses, :mod:`tuning.design.calibration`);
    ``executor``: the command's helpers for the exact runs."""
    if joint is None or joint.design is None:
        return None
    u, cart_design = joint.uncertainty, joint.design
    say("Part (v): the designs on the cart as measured, with their bands and margins")
    steps = [r for r in recordings if is_step(r)]
    misses = tuple(
        step_miss(own_cart(joint, r, held_out=True), r, held_values(joint, r) is not None)
        for r in steps
    )
    error = model_error(misses)
    ran = None if rec is None or rec.controller is None else rec.controller
    chosen = [
        ("prelab", prelab_gains, None),
        ("retuned", cart_design.gains, cart_design.prediction),
    ]
    if ran is not None and not any(same_gains(ran, g) for _, g, _ in chosen):
        chosen.append(("recording", ran, None))
    designs = []
    for key, controller, known in chosen:
        this_ran = ran is not None and same_gains(ran, controller)
        if this_ran:  # the run's own step and horizon
            prediction = predict(u, ran, experiment=rec.experiment, executor=executor)
        else:
            prediction = known or predict(u, controller, executor=executor)
        prediction = dataclasses.replace(prediction, model_error=error)
        extra = _measured(rec, prediction) if this_ran else {}
        fitted = margins(u.nominal_cart(), controller)
        designs.append(Design(key, controller, prediction, fitted, **extra))
    name = None if rec is None else rec.path.name
    runs = {n: len(v) for n, v in u.drive.items()}
    return Designs(tuple(designs), name, joint.source, misses, error, runs)


def own_cart(joint, recording, held_out: bool = False):
    """The fitted cart with the recording's own drive values (``v_sat@k`` of its run k in the
    joint fit), the others at the runs' mean; ``held_out``: the cart fitted without the
    recording where the joint fit held it out (:func:`held_values`), with its own drive values
    fitted to it alone."""
    u = joint.uncertainty
    values = u.nominal()
    names = list(joint.names)
    if recording.path.name not in names:
        return u.cart(values)
    k = names.index(recording.path.name)
    held = held_values(joint, recording) if held_out else None
    fitted = {n: e.value for n, e in joint.fit.params.items()} if held is None else held
    for n, v in fitted.items():
        base, _, run = n.partition("@")
        shared = run == "" and held is not None  # in-sample: the fitted mean already
        if v is not None and base in values and (shared or run == str(k)):
            values[base] = float(v)
    return u.cart(values)


def held_values(joint, recording) -> dict | None:
    """The values of the joint fit that left ``recording`` out ({name: value [SI]},
    :attr:`tuning.estimation.fitting.result.SegmentFit.held_out`), None where it was not held
    out (a fit of the lab's own, a single recording, a run only it determines)."""
    names = list(joint.names)
    if recording.path.name not in names:
        return None
    return joint.fit.segments[names.index(recording.path.name)].held_out


def _measured(rec, prediction: Prediction) -> dict:
    """The recording's metrics, its run and its check against ``prediction``."""
    info = jc.step_info(rec.as_response(), v_limit=V_SAT)
    metrics = {"settling_time": info.settling_time, "overshoot": info.overshoot}
    return {
        "measured": info,
        "run": (np.asarray(rec.time, dtype=float), np.asarray(rec.position, dtype=float)),
        "check": check_run(metrics, prediction.to_json()),
    }


def values(d: Designs | None) -> list:
    """The summary's numbers: each design's chance of meeting the spec."""
    if d is None:
        return []
    return [
        value(f"pid_{x.key}_p_meet", x.prediction.p_meet, "", f"P(spec), {x.label}", "v")
        for x in d.designs
    ]


def to_json(d: Designs | None) -> dict | None:
    if d is None:
        return None
    out = {"model_error": d.model_error, "misses": [m.to_json() for m in d.misses], "designs": []}
    for x in d.designs:
        entry = {
            "design": x.key,
            "label": x.label,
            "controller": x.controller.to_dict(),
            "prediction": x.prediction.to_json(),
            "margins": x.margins.to_json(),
        }
        if x.measured is not None:
            entry["measured"] = x.measured.as_dict()
            entry["check"] = _plain_check(x.check)
        out["designs"].append(entry)
    return out


def _plain_check(check: dict) -> dict:
    """The check with its bands as lists (JSON)."""
    rows = [{**r, "band": list(r["band"])} for r in check["metrics"]]
    return {"inside": check["inside"], "level": check["level"], "metrics": rows}
