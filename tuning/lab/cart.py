"""The cart fitted once, jointly, from every recording of the lab (one cart, one story).

A real cart is one set of mechanics across its recordings (B_eq, f_c), while its drive does not
repeat itself: the amplifier limit differs from run to run as the motor warms and the supply
sags. :func:`compute` fits every recording at once with the mechanics shared and the limit
v_sat free in each driven run (:func:`tuning.estimation.fit.fit`, ``per_recording``), fits
the driven runs alone to say whether their B_eq agrees with the tap's under that model, and
re-tunes the PID on the fitted cart; :func:`render` writes the section and the plant file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from jaxcart import plantspec
from tuning.lab.context import Lab, fmt, value

#: The joint model: viscous and Coulomb friction shared, the amplifier limit per driven run.
PARAMS = ("B_eq", "f_c", "v_sat")
PER_RUN = "v_sat"
#: The file the report writes the fitted cart into (for simulate, tune, grid, lab --plant).
PLANT_FILE = "cart_plant.toml"


@dataclass(frozen=True)
class JointCart:
    """fit: the joint fit (every recording); driven: the driven runs alone (None without a
    tap to compare with); tap: Part (i)'s (B_eq, its standard error) [kg/s] or None; tuned:
    :class:`tuning.design.tune.TuneResult` of the PID re-tuned on the fitted cart (None when
    no fit was possible); names: each recording's file name."""

    fit: object
    driven: object
    tap: tuple | None
    tuned: object
    names: tuple

    @property
    def plant(self):
        """The fitted cart (the drive's limit at the median of the runs)."""
        return self.fit.plant()

    def agreement(self) -> tuple[float, float] | None:
        """(difference of the driven runs' B_eq from the tap's [kg/s], in standard errors of
        the difference), or None without both."""
        if self.tap is None or self.driven is None:
            return None
        b = self.driven.params["B_eq"]
        if b.value is None:
            return None
        diff = b.value - self.tap[0]
        se = math.hypot(b.stderr or 0.0, self.tap[1] or 0.0)
        return diff, abs(diff) / se if se > 0 else math.inf


def structure(inputs, diagnosis=None) -> tuple[tuple, tuple]:
    """(parameters fitted, those free per driven run): the joint diagnosis's structure where
    there is one; else B_eq, f_c and v_sat, v_sat per run where a part was run twice (the
    evidence that the drive varies)."""
    if diagnosis is not None and diagnosis.status == "diagnosed":
        per = sorted({n for r in diagnosis.per_recording.values() for n in r["parameters"]})
        return tuple(diagnosis.parameters) + tuple(per), tuple(per)
    return PARAMS, (PER_RUN,) if inputs.repeats else ()


def compute(
    inputs, tap_b_eq=None, diagnosis=None, *, start=None, fit=None, say=lambda t: None
) -> JointCart | None:
    """The joint fit of every recording of ``inputs`` (:class:`tuning.lab.inputs.Inputs`,
    repeats included) with :func:`structure`; ``tap_b_eq``: Part (i)'s (value, stderr);
    ``start``: the cart as the parts left it ({name: value}), where the fits start (the
    diagnosis's values where there is one) and, from there, only polish;
    ``fit``: the lab's fitter (:func:`tuning.lab.fits.fit`). None without a driven run."""
    from tuning.design.tune import tune
    from tuning.lab import fits
    from tuning.lab.prelab import TUNE_OPTIONS

    fit = fit or fits.fit

    runs = inputs.runs()
    driven = [r for r in runs if r.kind != "tap"]
    if not driven:
        return None
    params, per = structure(inputs, diagnosis)
    per = per if len(driven) >= 2 else ()
    say(f"the cart: one joint fit of {len(runs)} recordings ({', '.join(params)})")
    initial = _start(params, diagnosis, start or {})
    joint = fit(runs, params, per_recording=per, initial=initial, quick=bool(initial))
    alone = None
    if len(driven) < len(runs) and tap_b_eq is not None:
        say("the cart: the driven runs alone, for B_eq beside the tap's")
        alone = fit(driven, params, per_recording=per, initial=initial, quick=bool(initial))
    say("the cart: the PID re-tuned on the fitted cart")
    tuned = tune(_design_plant(joint), progress=False, **TUNE_OPTIONS)
    names = tuple(s.name for s in joint.segments)
    return JointCart(joint, alone, tap_b_eq, tuned, names)


def _start(params, diagnosis, before: dict) -> dict:
    """Start values of the joint fit: the diagnosis's (shared values, each drive limit at the
    median of its runs), else the parts' ({} without them: the fit's own continuation)."""
    import numpy as np

    out = {k: v for k, v in before.items() if k in params}
    if diagnosis is not None and diagnosis.status == "diagnosed":
        out.update({n: p["value"] for n, p in diagnosis.parameters.items() if n in params})
        own = {}
        for rec in diagnosis.per_recording.values():
            for n, p in rec["parameters"].items():
                own.setdefault(n, []).append(p["value"])
        out.update({n: float(np.median(v)) for n, v in own.items()})
    return out


def _design_plant(joint):
    """The fitted cart as the tuner's design model: its mechanics and drive, without the
    sensor (the tuner's loop reads the position itself)."""
    import dataclasses

    plant = joint.plant()
    return dataclasses.replace(
        plant, effects=tuple(e for e in plant.effects if e.stage != "sensor")
    )


def model_of(c: JointCart | None, before):
    """The lab's :class:`tuning.lab.model.CartModel` after the joint fit (``before`` without
    one): Part (v) simulates the measured run on it."""
    import dataclasses

    if c is None:
        return before
    e = c.fit.params
    b, f = e["B_eq"], e.get("f_c")
    where = "the joint fit of every recording"
    model = dataclasses.replace(
        before, B_eq=b.value, B_eq_source=where, B_eq_stderr=b.stderr, base=c.plant
    )
    if f is not None and f.value is not None:
        model = dataclasses.replace(model, f_c=f.value, f_c_source=where)
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


def as_json(c: JointCart | None) -> dict | None:
    if c is None:
        return None
    agree = c.agreement()
    g = c.tuned.gains
    return {
        "fit": c.fit.to_json(),
        "driven_only_B_eq": None if c.driven is None else c.driven.params["B_eq"].to_json(),
        "tap_B_eq": None if c.tap is None else {"value": c.tap[0], "stderr": c.tap[1]},
        "B_eq_difference": None if agree is None else {"kg/s": agree[0], "sigmas": agree[1]},
        "retuned": {"kp": g.kp, "ki": g.ki, "kd": g.kd, "meets": c.tuned.meets},
        "plant_file": PLANT_FILE,
    }


def render(lab: Lab, c: JointCart | None) -> None:
    """The section 'The cart, fitted once from every recording' and its plant file."""
    doc = lab.doc
    doc.heading("The cart, fitted once from every recording")
    if c is None:
        doc.paragraph("No driven recording was given: the cart is the tap's (Part (i)).")
        return
    from jaxcart.plantspec import write_plant_file

    write_plant_file(lab.out / PLANT_FILE, c.plant, fit={"source": "jaxcart lab, joint fit"})
    doc.paragraph(
        f"Every recording ({', '.join(c.names)}) is fitted at once on one cart: B_eq and f_c "
        "shared, and in each driven run its own amplifier limit v_sat (a real drive does not "
        "repeat itself: the motor warms, the supply sags). The fitted cart is written to "
        f"`{PLANT_FILE}` (for `jaxcart simulate`, `tune`, `grid`, `lab --plant`), with the "
        "drive's limit at the median of the runs."
    )
    rows = []
    for name, est in c.fit.params.items():
        base, _, k = name.partition("@")
        who = c.names[int(k)] if k else "every recording"
        if est.value is None:
            rows.append([base, who, "held", "-", est.note])
        else:
            rows.append([base, who, fmt(est.value), fmt(est.stderr, 2), ""])
    doc.table(["parameter", "recording", "value", "standard error", "note"], rows)
    doc.table(
        ["recording", "RMS error of the fitted cart [mm] (exact simulator)"],
        [[s.name, _mm(s.rms_after_exact)] for s in c.fit.segments],
        numeric=[False, True],
    )
    doc.paragraph(_agreement_text(c))
    g, t = c.tuned.gains, c.tuned
    doc.paragraph(
        f"Part (v) on this cart: the PID re-tuned on it is kp = {fmt(g.kp)} V/m, ki = "
        f"{fmt(g.ki)} V/(m s), kd = {fmt(g.kd)} V s/m; on the exact simulator it settles in "
        f"{fmt(t.exact.settling_time)} s with {fmt(t.exact.overshoot)} % overshoot "
        f"({'meets' if t.meets else 'does not meet'} the handout's spec)."
    )


def _agreement_text(c: JointCart) -> str:
    agree = c.agreement()
    if agree is None:
        return "Without a tap and a driven run there is no second B_eq to compare."
    diff, sigmas = agree
    b = c.driven.params["B_eq"]
    from tuning.estimation.engine.parameters import bounds

    lo, hi = bounds("B_eq")
    if not lo * 1.02 < b.value < hi / 1.02:
        return (
            f"B_eq from the tap (Part (i)) is {fmt(c.tap[0])} ± {fmt(c.tap[1], 2)} kg/s. The "
            f"driven runs alone do not pin it under this model: their fit runs to the edge of "
            f"what a cart of this lab has ({fmt(b.value)} kg/s, range {fmt(lo)}-{fmt(hi)} "
            "kg/s), so B_eq is the tap's to give, and the joint fit above takes it from there."
        )
    verdict = "agree" if sigmas <= 2 else "disagree"
    return (
        f"B_eq from the tap (Part (i)) is {fmt(c.tap[0])} ± {fmt(c.tap[1], 2)} kg/s; from the "
        f"driven runs alone under this model {fmt(b.value)} ± {fmt(b.stderr, 2)} kg/s: they "
        f"{verdict} ({fmt(diff, 2)} kg/s apart, {sigmas:.1f} standard errors)."
    )


def _mm(x) -> str:
    return "n/a" if x is None else fmt(float(x) * 1e3, 3)
