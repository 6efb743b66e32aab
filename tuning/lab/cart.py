"""The cart fitted once, jointly, from every recording of the lab (one cart, one story).

A real cart is one set of mechanics across its recordings (B_eq, f_c), while its drive does not
repeat itself: the amplifier limit differs from run to run as the motor warms and the supply
sags. The lab's joint diagnosis (:mod:`tuning.lab.diagnosis`) ends with exactly that fit: its
chosen structure over every recording, the mechanics shared and a drive limit free per run
where the data show one, and the same structure on the driven runs alone, for a B_eq beside
the tap's. :func:`compute` takes the cart from there (fitting only where there is no
diagnosis: ``--no-diagnosis``, or recordings it could not diagnose, with
:func:`tuning.estimation.fit.fit`, ``per_recording``), with its uncertainty (the fit's standard
errors and the drive's spread from run to run, :mod:`tuning.design.uncertainty`); :func:`retune`
tunes the PID for the cart as measured (:func:`tuning.design.for_cart.design_for_cart`: robust
over that uncertainty, inside the limits the cart sets; the lab runs it beside Part (v) and
puts its result in the cart with :func:`with_retune`); :func:`render` writes the section and
the plant file (its [fit] table holds the uncertainty, for ``jaxcart tune --plant ...
--robust``).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

from jaxcart import plantspec
from jaxcart.plantspec import write_plant_file
from tuning.design import uncertainty as cart_uncertainty
from tuning.design.for_cart import design_for_cart
from tuning.estimation.engine.parameters import bounds
from tuning.estimation.fit import Estimate, FitSettings, default_start
from tuning.lab import fits
from tuning.lab.context import Lab, fmt, value

#: The joint model without a diagnosis: viscous and Coulomb friction shared, the amplifier
#: limit per driven run.
PARAMS = ("B_eq", "f_c", "v_sat")
PER_RUN = "v_sat"
#: The file the report writes the fitted cart into (for simulate, tune, grid, lab --plant).
PLANT_FILE = "cart_plant.toml"


@dataclass(frozen=True)
class JointCart:
    """fit: the joint fit of every recording (a :class:`tuning.estimation.fit.FitResult`: the
    diagnosis's, :attr:`tuning.estimation.diagnose.result.Diagnosis.fit`, or a fit of its own);
    driven: B_eq of the driven runs alone (an :class:`~tuning.estimation.fit.Estimate`; None
    without a tap to compare with); tap: Part (i)'s (B_eq, its standard error) [kg/s] or None;
    names: each recording's file name; source: where the fit comes from, in words; tuned: the
    PID re-tuned on the fitted cart (a :class:`tuning.design.result.TuneResult`; None until
    the lab has it: :func:`retune`, :func:`with_retune`); uncertainty: the fit's
    (:class:`tuning.design.uncertainty.CartUncertainty`); design: the PID tuned for the cart as
    measured (a :class:`tuning.design.for_cart.CartDesign`; None until the lab has it)."""

    fit: object
    driven: object
    tap: tuple | None
    names: tuple
    source: str = "the joint diagnosis"
    uncertainty: object = None
    design: object = None

    @property
    def plant(self):
        """The fitted cart (the drive's limit at the median of the runs)."""
        return self.fit.plant()

    @property
    def tuned(self):
        """The design's :class:`tuning.design.result.TuneResult` (None before the re-tune)."""
        return None if self.design is None else self.design.tuned

    def agreement(self) -> tuple[float, float] | None:
        """(difference of the driven runs' B_eq from the tap's [kg/s], in standard errors of
        the difference), or None without both, or where the driven runs' fit ran to the edge
        of a lab cart's range (a value there is the bound's, and its standard error says
        nothing of the distance)."""
        if self.tap is None or self.driven is None:
            return None
        b = self.driven
        if b.value is None or _at_edge(b):
            return None
        diff = b.value - self.tap[0]
        se = math.hypot(b.stderr or 0.0, self.tap[1] or 0.0)
        return diff, abs(diff) / se if se > 0 else math.inf


def structure(inputs) -> tuple[tuple, tuple]:
    """(parameters fitted, those free per driven run) of a joint fit without a diagnosis:
    B_eq, f_c and v_sat, v_sat per run where a part was run twice (the evidence that the drive
    varies)."""
    return PARAMS, (PER_RUN,) if inputs.repeats else ()


def compute(
    inputs, tap_b_eq=None, diagnosis=None, *, start=None, fit=None, say=lambda t: None
) -> JointCart | None:
    """The cart of every recording of ``inputs`` (:class:`tuning.lab.inputs.Inputs`, repeats
    included): the diagnosis's fit where ``diagnosis`` (its
    :class:`~tuning.estimation.diagnose.Diagnosis`) diagnosed the recordings, else fitted in
    :func:`structure`'s parameters;
    ``tap_b_eq``: Part (i)'s (value, stderr); ``start``: the cart as the parts left it ({name:
    value}), where a fit of its own starts; ``fit``: the lab's fitter
    (:func:`tuning.lab.fits.fit`). None without a driven run. The PID is not re-tuned here
    (:func:`retune`)."""
    runs = inputs.runs()
    if not any(r.kind != "tap" for r in runs):
        return None
    if diagnosis is not None and diagnosis.status == "diagnosed":
        joint, alone = _diagnosed(diagnosis, tap_b_eq, say)
        source = "the joint diagnosis"
    else:
        joint, alone = _fitted(inputs, runs, tap_b_eq, start or {}, fit, say)
        source = "a joint fit of its own (no diagnosis)"
    names = tuple(s.name for s in joint.segments)
    uncertain = cart_uncertainty.from_fit(joint, source=source)
    return JointCart(joint, alone, tap_b_eq, names, source, uncertain)


def retune(c: JointCart, executor=None):
    """The PID tuned for the cart as measured, with ``jaxcart tune``'s settings (one tuner, one
    answer), robust over the fit's uncertainty: a :class:`tuning.design.for_cart.CartDesign`
    (its prediction's exact runs through ``executor``, the command's helpers, where given)."""
    return design_for_cart(c.uncertainty, executor=executor)


def with_retune(c: JointCart | None, design) -> JointCart | None:
    """The cart with its design (:func:`retune`'s result)."""
    return None if c is None else dataclasses.replace(c, design=design)


def _diagnosed(diagnosis, tap_b_eq, say):
    """(the diagnosis's joint fit, B_eq of its driven runs alone or None)."""
    if diagnosis.fit is None:
        raise ValueError(f"the diagnosis has no fit (status {diagnosis.status!r})")
    joint = diagnosis.fit
    say(f"the cart: the diagnosis's joint fit of {len(joint.segments)} recordings")
    b = diagnosis.driven_alone.get("parameters", {}).get("B_eq")
    alone = None
    if b is not None and tap_b_eq is not None:
        alone = Estimate("B_eq", b["value"], b["stderr"])
    return joint, alone


def _fitted(inputs, runs, tap_b_eq, start, fit, say):
    """(a joint fit of ``runs``, B_eq of the driven runs fitted alone or None): without a
    diagnosis, in :func:`structure`'s parameters from the parts' values; the driven runs
    alone from the joint fit's values, by the exact polish alone where every value is shared
    (:meth:`FitSettings.exact_only`; as a diagnosis re-fits them, ``crossval.driven_alone``)."""
    fit = fit or fits.fit
    driven = [r for r in runs if r.kind != "tap"]
    params, per = structure(inputs)
    per = per if len(driven) >= 2 else ()
    many = "s" if len(runs) != 1 else ""
    say(f"the cart: one joint fit of {len(runs)} recording{many} ({', '.join(params)})")
    initial = {k: v for k, v in start.items() if k in params}
    near = FitSettings.warm() if initial else None
    joint = fit(runs, params, per_recording=per, initial=initial, settings=near)
    alone = None
    if len(driven) < len(runs) and tap_b_eq is not None:
        say("the cart: the driven runs alone, for B_eq beside the tap's")
        if per:  # a run's own drive value cannot start where the joint fit put it (one start)
            alone = fit(driven, params, per_recording=per, initial=initial, settings=near)
        else:
            at = {**initial, **{k: e.value for k, e in joint.params.items() if e.identifiable}}
            alone = fit(driven, params, initial=at, settings=FitSettings.exact_only())
        alone = alone.params["B_eq"]
    return joint, alone


def model_of(c: JointCart | None, before):
    """The lab's :class:`tuning.lab.model.CartModel` after the joint fit (``before`` without
    one): Part (v) simulates the measured run on it."""
    if c is None:
        return before
    e = c.fit.params
    b, f = e["B_eq"], e.get("f_c")
    where = "the joint fit of every recording"
    if b.value is None:  # not identified: the fit held it (its note says at what and why)
        b_value, where_b = b.held_at, f"{where}, which held it at {fmt(b.held_at)} kg/s"
    else:
        b_value, where_b = b.value, where
    model = dataclasses.replace(
        before, B_eq=b_value, B_eq_source=where_b, B_eq_stderr=b.stderr, base=c.plant
    )
    if f is not None and f.value is not None:
        model = dataclasses.replace(model, f_c=f.value, f_c_source=where)
    elif f is not None and f.held_at is not None:  # the cart's plant holds it there
        held = f"{where}, which held it at {fmt(f.held_at)} N"
        model = dataclasses.replace(model, f_c=f.held_at, f_c_source=held)
    return model


def values(c: JointCart | None) -> list:
    """The summary's numbers of the joint fit."""
    if c is None:
        return []
    out = [
        value(f"cart_{n}", e.value, plantspec.unit(n), f"{n} of the cart, joint fit", "cart")
        for n, e in c.fit.params.items()
        if "@" not in n and e.value is not None
    ]
    g = c.tuned.gains
    out += [
        value(f"cart_pid_{n}", float(getattr(g, n)), u, f"PID {n} re-tuned on the cart", "cart")
        for n, u in (("kp", "V/m"), ("ki", "V/(m s)"), ("kd", "V s/m"))
    ]
    return out


def to_json(c: JointCart | None) -> dict | None:
    if c is None:
        return None
    agree = c.agreement()
    g = c.tuned.gains
    return {
        "fit": c.fit.to_json(),
        "source": c.source,
        "driven_only_B_eq": None if c.driven is None else c.driven.to_json(),
        "tap_B_eq": None if c.tap is None else {"value": c.tap[0], "stderr": c.tap[1]},
        "B_eq_difference": None if agree is None else {"kg/s": agree[0], "sigmas": agree[1]},
        "retuned": {
            "kp": g.kp,
            "ki": g.ki,
            "kd": g.kd,
            "meets": c.tuned.meets,
            "binding": c.design.binding,
            "prediction": c.design.prediction.to_json(),
            "margins": c.design.margins.to_json(),
        },
        "plant_file": PLANT_FILE,
    }


def render(lab: Lab, c: JointCart | None) -> None:
    """The section 'The cart, fitted once from every recording' and its plant file."""
    doc = lab.doc
    doc.heading("The cart, fitted once from every recording")
    if c is None:
        doc.paragraph("No driven recording was given: the cart is the tap's (Part (i)).")
        return

    fit = {"source": f"jaxcart lab, {c.source}", **cart_uncertainty.fit_table(c.uncertainty)}
    write_plant_file(lab.out / PLANT_FILE, c.plant, fit=fit)
    doc.paragraph(_structure_text(c))
    rows = []
    for name, est in c.fit.params.items():
        base, _, k = name.partition("@")
        who = c.names[int(k)] if k else "every recording"
        if est.value is None:
            rows.append([base, who, "held", "-", _named_runs(est.note, c.names)])
        else:
            rows.append([base, who, fmt(est.value), fmt(est.stderr, 2), ""])
    doc.table(["parameter", "recording", "value", "standard error", "note"], rows)
    wide = c.uncertainty.widened if c.uncertainty is not None else {}
    if wide:  # the design and its band draw from the wider spread
        doc.paragraph(
            "Fitted again with each recording left out in turn, the cart's values spread "
            "further than their standard errors say: "
            + ", ".join(
                f"{n} {fmt(a, 2)} -> {fmt(b, 2)} {plantspec.unit(n)}".rstrip()
                for n, (a, b) in wide.items()
            )
            + ". A standard error says how well the recordings pin a value if the model and "
            "its noise are right; the spread, how much the value depends on which recordings "
            "were fitted (a model that leaves something out, or noise that is not white, "
            "widens it). The design for the cart as measured and every band below draw from "
            "the wider of the two."
        )
    doc.table(
        ["recording", "RMS error of the fitted cart [mm] (exact simulator)"],
        [[s.name, _mm(s.rms_after_exact)] for s in c.fit.segments],
        numeric=[False, True],
    )
    assumed = _assumed(c)
    if assumed:  # the design below rests on values no recording gave
        doc.paragraph(
            f"**No recording determines {', '.join(assumed)}**: the cart holds "
            + ", ".join(f"{n} at {fmt(v)} (the {w})" for n, (v, w) in assumed.items())
            + f", its largest RMS error is {_mm(max(s.rms_after_exact for s in c.fit.segments))}"
            " mm, and the design and its band below rest on those values, not on this cart. "
            "A tap (Part (i)) determines B_eq, a ramp (Part (iii)) f_c."
        )
    held = {n for n, e in c.fit.params.items() if e.value is None}  # in the table above
    said = [w for w in c.fit.warnings if not any(w.startswith(f"{n}: ") for n in held)]
    if said:  # what the numbers do not show: a misfit, an optimizer stopped at its cap
        doc.paragraph("What the fit says of itself: " + "; ".join(said) + ".")
    doc.paragraph(_agreement_text(c))
    g, t, p = c.tuned.gains, c.tuned, c.design.prediction
    lo, hi = p.interval("settling_time")
    doc.paragraph(
        f"Part (v) on this cart: the PID tuned for the cart as measured (robust over "
        f"{len(t.plant_set or [])} carts drawn from this fit's uncertainty) is kp = "
        f"{fmt(g.kp)} V/m, ki = {fmt(g.ki)} V/(m s), kd = {fmt(g.kd)} V s/m; on the fitted "
        f"cart (exact simulator) it settles in {fmt(p.nominal['settling_time'])} s with "
        f"{fmt(p.nominal['overshoot'])} % overshoot, in {fmt(lo)}-{fmt(hi)} s on "
        f"{p.level:.0%} of carts drawn from the fit (the fit's band: Part (v) widens it by how "
        f"far the model misses the recorded steps), meeting the handout's spec on "
        f"{p.p_meet:.0%} of them (Part (v)'s P(spec) adds the model's miss). What limits "
        f"it: {c.design.binding}. Part (v) shows it beside "
        "the pre-lab's design, with its margins."
    )


def _structure_text(c: JointCart) -> str:
    """What the cart's fit is: its source, the values shared and those of each run."""
    shared = [n for n in c.fit.params if "@" not in n]
    own = sorted({n.partition("@")[0] for n in c.fit.params if "@" in n})
    text = (
        f"Every recording ({', '.join(c.names)}) is fitted at once on one cart, by "
        f"{c.source}: {', '.join(shared)} shared by every recording"
    )
    if own:
        text += (
            f", and in each driven run its own {', '.join(own)} (a real drive does not repeat "
            "itself: the motor warms, the supply sags)"
        )
    text += (
        f". The fitted cart is written to `{PLANT_FILE}` (for `jaxcart simulate`, `tune`, "
        "`grid`, `lab --plant`)"
    )
    return text + (", with each value of a run's own at the median of the runs." if own else ".")


def _named_runs(text: str, names) -> str:
    """``text`` with each run's own value named by its file (``v_sat@3``: v_sat of the fourth
    recording's file)."""
    return re.sub(r"\b(\w+)@(\d+)\b", lambda m: f"{m[1]} of {names[int(m[2])]}", text or "")


def _assumed(c: JointCart) -> dict:
    """{name: (value, whose)} of the cart's shared values that the joint fit held at the
    handout's or the effect's typical value (no part of the lab gave one)."""
    typical = {"B_eq": (plantspec.handout_plant().B_eq, "handout's estimate")}
    typical.update({n: (v, "typical value") for n, v in default_start().items() if n in ("f_c",)})
    out = {}
    for name, (v, whose) in typical.items():
        e = c.fit.params.get(name)
        if e is not None and e.value is None and math.isclose(e.held_at, float(v), rel_tol=1e-6):
            out[name] = (e.held_at, whose)
    return out


def _agreement_text(c: JointCart) -> str:
    agree = c.agreement()
    b = c.driven
    lo, hi = bounds("B_eq")
    if c.tap is not None and b is not None and b.value is not None and _at_edge(b):
        return (
            f"B_eq from the tap (Part (i)) is {fmt(c.tap[0])} ± {fmt(c.tap[1], 2)} kg/s. The "
            f"driven runs alone do not pin it under this model: their fit runs to the edge of "
            f"what a cart of this lab has ({fmt(b.value)} kg/s, range {fmt(lo)}-{fmt(hi)} "
            "kg/s), so B_eq is the tap's to give, and the joint fit above takes it from there."
        )
    if agree is None and c.tap is not None and b is not None:
        return (
            f"B_eq from the tap (Part (i)) is {fmt(c.tap[0])} ± {fmt(c.tap[1], 2)} kg/s. The "
            f"driven runs alone do not determine it under this model "
            f"({(c.driven.note or 'not identifiable').split(';')[0]}), so "
            "B_eq is the tap's to give, and the joint fit above takes it from there."
        )
    if agree is None:
        return "Without a tap and a driven run there is no second B_eq to compare."
    diff, sigmas = agree
    verdict = "agree" if sigmas <= 2 else "disagree"
    return (
        f"B_eq from the tap (Part (i)) is {fmt(c.tap[0])} ± {fmt(c.tap[1], 2)} kg/s; from the "
        f"driven runs alone under this model {fmt(b.value)} ± {fmt(b.stderr, 2)} kg/s: they "
        f"{verdict} ({fmt(diff, 2)} kg/s apart, {sigmas:.1f} standard errors)."
    )


def _at_edge(estimate) -> bool:
    """B_eq's ``estimate`` on (or within 2 % of) an edge of a lab cart's range: the bound's
    value, no estimate."""
    lo, hi = bounds("B_eq")
    return estimate.edge is not None or not lo * 1.02 < estimate.value < hi / 1.02


def _mm(x) -> str:
    return "n/a" if x is None else fmt(float(x) * 1e3, 3)
