"""The lab report's diagnosis section: for each recording, which physics the model left out and
the fit with it (``jaxcart diagnose`` on each recording; ``jaxcart diagnose`` on several files
diagnoses them jointly, one cart, which the report suggests rather than runs: it takes
minutes)."""

from __future__ import annotations

from tuning.lab.inputs import SLOTS

#: What each slot's recording is, for the table.
PARTS = {
    "tap": "(i) tap",
    "p_step": "(ii) P 50 step",
    "ramp": "(iii) open-loop ramp",
    "p_error": "(iii) P 10 step",
    "pi": "(iv) PI",
    "pid": "(v) PID",
}


def compute(recordings: dict, *, say=lambda text: None) -> dict:
    """Each recording diagnosed on its own: slot -> :class:`tuning.estimation.diagnose.Diagnosis`
    in the order of :data:`SLOTS`; ``recordings``: slot -> recording (or None)."""
    from tuning.estimation.diagnose import diagnose

    found = {}
    for slot in SLOTS:
        rec = recordings.get(slot)
        if rec:
            say(f"diagnosis: {PARTS[slot]} ({rec.path.name})")
            found[slot] = diagnose([rec], progress=False)
    return found


def as_json(found: dict) -> dict:
    return {slot: d.to_json() for slot, d in found.items()}


def render(lab, found: dict, agreement=None) -> None:
    """The diagnosis section from :func:`compute`'s results; ``agreement``: Part (ii)'s
    :class:`tuning.lab.part_ii.Agreement` of the tap's and the step's B_eq (or None)."""
    doc = lab.doc
    doc.heading("Diagnosis: what the model leaves out")
    if not found:
        doc.paragraph("No recordings were given, so there is nothing to diagnose.")
        return
    doc.paragraph(
        "Each recording is compared with the handout's model (equation (0.1), appendix values, "
        "B_eq fitted, the controller as its file describes it) on the exact simulator. Where "
        "they part by more than the encoder's quantization, candidate structures from the "
        "effects library (saturation, Coulomb friction, stiction, delay, deadzone, spring, "
        "current limit, pairs of them, and larger sets while a pair is not enough) and the "
        "parameter corrections (mass, motor gain) are fitted in batches and re-checked on the "
        "exact simulator; an information criterion with a penalty per added effect chooses "
        "among the structures whose every effect is significant, and a recording that no "
        "structure brings within 3 times the encoder floor is marked not explained. Part (ii) "
        "is the handout's own example of "
        "left-out physics: the ±6 V saturation, which the linear model (0.1) has not."
    )
    rows = [_row(PARTS[slot], lab.recording(slot).path.name, d) for slot, d in found.items()]
    doc.table(
        ["part", "recording", "left out", "RMS before [mm]", "RMS after [mm]", "fitted"],
        rows,
        numeric=[False, False, False, True, True, False],
    )
    b_eq = {k: d.parameters.get("B_eq", {}).get("value") for k, d in found.items()}
    b_eq = {k: v for k, v in b_eq.items() if v is not None}
    if len(b_eq) > 1:
        doc.paragraph(_b_eq_spread(b_eq, agreement))


def _b_eq_spread(b_eq: dict, agreement) -> str:
    spread = max(b_eq.values()) - min(b_eq.values())
    before = ""
    if agreement is not None:
        before = (
            f"With the handout's model (viscous and Coulomb friction only) Part (i) found "
            f"B_eq = {agreement.B_eq_tap:.4g} kg/s from the tap and Part (ii) "
            f"{agreement.B_eq_step:.4g} kg/s from the P 50 step. "
        )
    return (
        before + "B_eq is one cart's viscous friction, so a sound diagnosis gives the same "
        f"value from every recording: with the effects it found it ranges over "
        f"{spread:.3g} kg/s ("
        + ", ".join(f"{PARTS.get(k, k)}: {v:.3g}" for k, v in b_eq.items())
        + "). Where it still differs, or where no structure reaches the encoder floor, "
        "physics outside the library is at work. `jaxcart diagnose` on the files gives "
        "the windows, the residual tests and a figure for each, and diagnoses several "
        "files jointly (one plant, every file's controller)."
    )


def _row(part, name, d) -> list:
    if d.status != "diagnosed":
        return [part, name, d.status, "-", "-", "; ".join(d.messages)]
    if d.left_out:
        left = ", ".join(d.left_out)
    elif d.corrected_parameters:
        left = "nothing (corrected " + ", ".join(d.corrected_parameters) + ")"
    else:
        left = "nothing"
    if d.equivalent:
        left += " (or " + "; ".join(" + ".join(e) for e in d.equivalent) + ")"
    if d.left_out and d.corrected_parameters:
        left += "; corrected " + ", ".join(d.corrected_parameters)
    if not d.explained:
        left = (
            f"not explained: {d.floor_ratio:.3g}x the encoder floor with the best "
            f"approximation ({left})"
        )
    if d.unidentifiable:
        left += "; M and gamma_scale not told apart (B_eq not settled)"
    if d.implausible:
        left += "; implausible: " + "; ".join(d.implausible)
    fitted = ", ".join(
        f"{n} = {p['value']:.4g}" for n, p in d.parameters.items() if p.get("value") is not None
    )
    return [part, name, left, _mm(d.rms_before), _mm(d.rms_after), fitted]


def _mm(x) -> str:
    return f"{x * 1e3:.4g}"
