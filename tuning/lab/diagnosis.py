"""The lab report's diagnosis section: every recording at once, one cart (``jaxcart diagnose``
on all the files), which physics the model left out and the fit with it, each recording's own
drive values and RMS."""

from __future__ import annotations

from tuning.estimation.diagnose import diagnose

#: What each slot's recording is, for the table.
PARTS = {
    "tap": "(i) tap",
    "p_step": "(ii) P 50 step",
    "ramp": "(iii) open-loop ramp",
    "p_error": "(iii) P 10 step",
    "pi": "(iv) PI",
    "pid": "(v) PID",
}


def compute(inputs, say=lambda text: None, *, executor=None):
    """Every recording of the lab diagnosed jointly, one cart (repeats included): a
    :class:`tuning.estimation.diagnose.Diagnosis`, or None without recordings; ``executor``
    makes its exact runs (:func:`tuning.estimation.diagnose.diagnose`)."""
    runs = inputs.runs()
    if not runs:
        return None
    say(f"diagnosis: the {len(runs)} recordings jointly, one cart")
    return diagnose(runs, progress=False, executor=executor)


def to_json(d) -> dict | None:
    return None if d is None else d.to_json()


def _part_of(lab, name: str) -> str:
    """The part a recording's file name belongs to (repeats too), for the table."""
    for slot, rec in lab.inputs.recordings.items():
        if rec.path.name == name.split(" #")[0]:
            return PARTS[slot]
    for slot, recs in lab.inputs.repeats.items():
        if any(r.path.name == name.split(" #")[0] for r in recs):
            return PARTS[slot] + " (repeat)"
    return "-"


def render(lab, d, agreement=None) -> None:
    """The diagnosis section from :func:`compute`'s result; ``agreement``: Part (ii)'s
    :class:`tuning.lab.part_ii.Agreement` of the tap's and the step's B_eq (or None)."""
    doc = lab.doc
    doc.heading("Diagnosis: what the model leaves out")
    if d is None:
        doc.paragraph("No recordings were given, so there is nothing to diagnose.")
        return
    doc.paragraph(
        "Every recording is compared at once with the handout's model (equation (0.1), "
        "appendix values, B_eq fitted, each file's controller) on the exact simulator, as one "
        "cart: its mechanics shared by every recording, and, with several driven runs, the "
        "drive's limit free in each (a real amplifier does not repeat itself). Candidate "
        "structures from the effects library (saturation, Coulomb friction, stiction, delay, "
        "deadzone, spring, current limit, pairs and larger sets) and the parameter "
        "corrections (mass, motor gain) are fitted in batches and re-checked on the exact "
        "simulator; an information criterion with a penalty per added effect chooses among "
        "the structures whose every effect is significant and physically sized."
    )
    doc.paragraph(f"**{d.verdict}**")
    if d.status != "diagnosed":
        return
    rows = []
    for name, rec in d.per_recording.items():
        own = ", ".join(
            f"{n} = {p['value']:.4g} {p['unit']}"
            + ("" if p.get("acts", True) else " (does not act)")
            for n, p in rec["parameters"].items()
        )
        held = rec.get("predicted_rms")
        # Predicted by the others' fit (diagnose/crossval.py); "*": with the joint values.
        held = "-" if held is None else _mm(held) + ("" if rec.get("held_out", True) else "*")
        rows.append(
            [
                _part_of(lab, name),
                name,
                own or "-",
                _mm(rec["rms_before"]),
                _mm(rec["rms_after"]),
                held,
            ]
        )
    doc.table(
        [
            "part",
            "recording",
            "its own values",
            "RMS before [mm]",
            "RMS after [mm]",
            "held out [mm]",
        ],
        rows,
        numeric=[False, False, False, True, True, True],
    )
    doc.paragraph(
        "Held out: each recording predicted by the cart fitted to the others alone (a value "
        "free per run at the other runs' median; * where the others cannot determine it, "
        "predicted with the joint values). A correct model predicts a recording it was not "
        "fitted to about as well as it fits it."
    )
    fitted = ", ".join(
        f"{n} = {p['value']:.4g} ± {p['stderr']:.2g} {p['unit']}"
        for n, p in d.parameters.items()
        if p.get("value") is not None
    )
    doc.paragraph(f"The cart's values (shared by every recording): {fitted}.")
    if agreement is not None:
        doc.paragraph(
            f"With the handout's model (viscous and Coulomb friction only) Part (i) found "
            f"B_eq = {agreement.B_eq_tap:.4g} kg/s from the tap and Part (ii) "
            f"{agreement.B_eq_step:.4g} kg/s from the P 50 step; the joint model above is "
            "one cart for both (the next section compares them under it). `jaxcart diagnose` "
            "on the files gives the windows, the residual tests and a figure."
        )


def _mm(x) -> str:
    return f"{x * 1e3:.4g}"
