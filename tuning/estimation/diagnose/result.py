"""What a diagnosis found: :class:`Diagnosis`, its verdict in words and its JSON.

:func:`tuning.estimation.diagnose.search.diagnose` makes it; :mod:`.report` draws and writes
it; each of its candidate structures holds its fit as a fit's result, the chosen one's is
:attr:`Diagnosis.fit`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tuning.estimation.engine.noise import MISFIT_RATIO


@dataclass
class Diagnosis:
    """What :func:`diagnose` found (see :meth:`to_json` for the fields).

    left_out / corrected_parameters: the effects and parameter corrections of the chosen
    structure (the corrected plant holds them). When ``explained`` is False no candidate
    reaches :data:`tuning.estimation.engine.noise.MISFIT_RATIO` times the encoder floor: the chosen
    structure is
    only the best approximation, and the verdict says so first."""

    recordings: list
    status: str  # "diagnosed" | "not diagnosed"
    messages: list
    controller_checks: list
    left_out: list = field(default_factory=list)
    corrected_parameters: list = field(default_factory=list)
    equivalent: list = field(default_factory=list)
    rms_before: float = math.nan
    rms_after: float = math.nan
    floor: float = math.nan
    parameters: dict = field(default_factory=dict)
    baseline: dict = field(default_factory=dict)
    windows: list = field(default_factory=list)
    tests: dict = field(default_factory=dict)
    candidates: list = field(default_factory=list)
    chosen: str = ""
    plant: object = None
    plant_file: str | None = None
    seconds: float = math.nan
    traces: list = field(default_factory=list)  # per segment: time, measured, baseline, after
    #: False when the best structure still ends above MISFIT_RATIO times the encoder floor.
    explained: bool = True
    #: Why the best structure does not explain the recording ("" when it does).
    misfit: str = ""
    #: What may be missing when nothing explains the recording (one phrase each).
    suggestions: list = field(default_factory=list)
    #: Fitted values of the chosen structure that a real cart does not have (one line each).
    implausible: list = field(default_factory=list)
    #: Effects a better-scoring structure had but which are not significant:
    #: [{"structure", "effect", "z", "why"}].
    not_significant: list = field(default_factory=list)
    #: Significance z of each named effect and correction (:func:`significance`).
    significance: dict = field(default_factory=dict)
    #: M and gamma_scale told apart or not: {} when they are (or neither is corrected), else
    #: {"parameters", "ratios", "alternatives", "B_eq", "note"}.
    unidentifiable: dict = field(default_factory=dict)
    #: The start plant's values of the corrected parameters (the corrections are from these).
    start_values: dict = field(default_factory=dict)
    #: Each recording: its own values of the parameters free per run ({"parameters": {name:
    #: {"value", "stderr", "unit", "acts"}}}; "acts" False for a limit above what the run
    #: drove, not determined there), its RMS before and after [m].
    per_recording: dict = field(default_factory=dict)
    #: Where a run's own drive limit is far below what another run drew: more than one drive
    #: varies (said beside the limits; "" otherwise).
    drive_spread: str = ""
    #: What the cart repeats [m]: the RMS spread of repeated runs of one experiment (None
    #: without repeats); below it a model of the cart cannot be judged.
    repeat: float | None = None
    #: What the best structure leaves, in words ("white noise", "a ripple at 7 Hz ...").
    remainder: str = ""
    #: Several recordings: each left out of the chosen structure's fit and predicted
    #: (:func:`tuning.estimation.diagnose.crossval.cross_validate`; {} for one recording).
    cross_validation: dict = field(default_factory=dict)
    #: With a tap and driven runs: the chosen structure fitted on the driven runs alone
    #: (:func:`tuning.estimation.diagnose.crossval.driven_alone`; {"recordings": names,
    #: "parameters": {name: {"value", "stderr", "unit"}}, "rms" [m]}), else {}.
    driven_alone: dict = field(default_factory=dict)
    #: The same on the taps alone (:func:`tuning.estimation.diagnose.crossval.taps_alone`):
    #: the tap's B_eq beside the driven runs', a consistency check of the one cart.
    taps_alone: dict = field(default_factory=dict)
    #: Not explained, with ``diagnose(curve=True)``: friction read as a curve of the speed and
    #: of the position (:func:`tuning.estimation.diagnose.friction_curve.discover`, its
    #: "plant" aside), else {}.
    friction_curve: dict = field(default_factory=dict)
    #: That curve's fitted cart (a :class:`jaxcart.Plant`), or None.
    curve_plant: object = None

    @property
    def fit(self):
        """The chosen structure's fit (its candidate's :attr:`~.structures.Candidate.result`:
        a :class:`~tuning.estimation.fitting.result.FitResult`, the cart that ``jaxcart lab``
        takes instead of fitting again); None where nothing was diagnosed."""
        chosen = next((c for c in self.candidates if c.name == self.chosen), None)
        return None if chosen is None else chosen.result

    @property
    def floor_ratio(self) -> float:
        return self.rms_after / self.floor if self.floor > 0 else math.nan

    def _found(self, spread: bool = True) -> list:
        found = []
        if self.left_out:
            found.append("left out: " + ", ".join(self.left_out))
        if self.corrected_parameters:
            parts = []
            for n in self.corrected_parameters:
                value = self.parameters.get(n, {}).get("value")
                unit = self.parameters.get(n, {}).get("unit", "")
                was = self.start_values.get(n)
                if value is None:
                    parts.append(n)
                elif was is None:
                    parts.append(f"{n} = {value:.4g} {unit}".rstrip())
                else:
                    parts.append(f"{n} {was:.4g} -> {value:.4g} {unit}".rstrip())
            found.append("corrected parameters: " + ", ".join(parts))
        own = [
            f"{n} = {p['value']:.4g}{(' ' + p['unit']).rstrip()} in {name}"
            for name, rec in self.per_recording.items()
            for n, p in rec.get("parameters", {}).items()
            if p.get("acts", True)
        ]
        if own:
            note = f" ({self.drive_spread})" if spread and self.drive_spread else ""
            found.append("the drive differs from run to run: " + ", ".join(own) + note)
        return found

    def _context(self) -> str:
        """What the remainder is, and what the cart repeats, for a verdict."""
        parts = []
        if self.repeat is not None:
            parts.append(
                f"the cart repeats itself to {self.repeat * 1e3:.3g} mm (repeated runs of one "
                "experiment)"
            )
        if self.remainder:
            parts.append(f"what is left is {self.remainder}")
        return "; ".join(parts)

    @property
    def verdict(self) -> str:
        if self.status != "diagnosed":
            return "not diagnosed: " + "; ".join(self.messages)
        found = self._found()
        if not self.explained:
            best = "; ".join(found) if found else "the baseline, nothing added"
            text = f"not explained: the best approximation ({best}) " + (
                "leaves " + self.misfit.split(" leaves ", 1)[1]
                if " leaves " in self.misfit
                else f"ends at {_times(self.floor_ratio)} times the encoder floor (RMS "
                f"{self.rms_after * 1e3:.4g} mm, floor {self.floor * 1e3:.2g} mm)"
            )
            if self._context():
                text += "; " + self._context()
            if self.suggestions:
                text += "; what may be missing: " + "; ".join(self.suggestions)
        elif self.repeat is not None and self.floor_ratio > MISFIT_RATIO:
            text = (
                f"explained to {self.rms_after * 1e3:.3g} mm RMS: "
                + ("; ".join(found) if found else "nothing left out")
                + "; every recording is predicted within what it repeats"
            )
            if self._context():
                text += "; " + self._context()
        elif found:
            text = "; ".join(found)
            if not self.left_out:
                text += "; nothing left out"
        else:
            text = "nothing left out: the baseline explains the recording to the encoder floor"
        if self.equivalent:
            text += "; fits equally well: " + "; ".join(" + ".join(e) for e in self.equivalent)
        if self.unidentifiable:
            text += "; " + self.unidentifiable["note"]
        if self.implausible:
            text += "; implausible: " + "; ".join(self.implausible)
        if self.cross_validation.get("text"):
            text += "; " + self.cross_validation["text"]
        curve = self.friction_curve
        for shape, of in ((curve, "the speed"), (curve.get("track", {}), "the position")):
            if shape.get("words"):
                named = "named" if shape.get("named") else "tried, not named"
                text += f"; friction as a curve of {of} ({named}): {shape['words']}"
        return text

    @property
    def headline(self) -> str:
        """A short form of the verdict (the figure's title)."""
        if self.status != "diagnosed":
            return self.verdict
        found = self._found(spread=False)  # the title: the caution is in the verdict
        if not self.explained:
            text = (
                f"NOT EXPLAINED: best approximation ({'; '.join(found) or 'baseline'}) at "
                f"{_times(self.floor_ratio)}x the encoder floor"
            )
        else:
            text = "; ".join(found) or "nothing left out"
        if self.unidentifiable:
            text += "; M and gamma_scale not told apart (B_eq not settled)"
        if self.implausible:
            text += "; implausible: " + ", ".join(
                line.split(" is ")[0].split(" sits ")[0] for line in self.implausible
            )
        return text

    def to_json(self) -> dict:
        return {
            "recordings": self.recordings,
            "status": self.status,
            "verdict": self.verdict,
            "messages": self.messages,
            "controller_checks": self.controller_checks,
            "left_out": self.left_out,
            "corrected_parameters": self.corrected_parameters,
            "equivalent": self.equivalent,
            "chosen": self.chosen,
            "explained": self.explained,
            "misfit": self.misfit,
            "suggestions": self.suggestions,
            "implausible": self.implausible,
            "not_significant": self.not_significant,
            "significance": self.significance,
            "unidentifiable": self.unidentifiable,
            "start_values": self.start_values,
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "encoder_floor": self.floor,
            "floor_ratio": self.floor_ratio,
            "parameters": self.parameters,
            "baseline": self.baseline,
            "windows": self.windows,
            "tests": self.tests,
            "candidates": [c.to_json() for c in self.candidates],
            "plant_file": self.plant_file,
            "seconds": self.seconds,
            "per_recording": self.per_recording,
            "drive_spread": self.drive_spread,
            "repeat": self.repeat,
            "remainder": self.remainder,
            "cross_validation": self.cross_validation,
            "driven_alone": self.driven_alone,
            "taps_alone": self.taps_alone,
            "friction_curve": self.friction_curve,
        }


def _times(ratio: float) -> str:
    """A multiple of the floor: one decimal below 10 (3.2, not 3, next to the 3 x rule)."""
    return f"{ratio:.1f}" if ratio < 10 else f"{ratio:.0f}"
