"""What every section of the lab report shares: the output folder, the document, the numbers
found so far (with units, where they came from and, for synthetic data, the truth) and the
best-known model of the cart that later parts simulate with.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from jaxcart.params import Plant
from jaxcart.plantspec import build_plant, with_values
from tuning.lab.html import Document
from tuning.lab.inputs import Inputs

#: The handout's estimate of B_eq [kg/s], used until a recording says otherwise.
HANDOUT_B_EQ = 5.4
#: Amplifier saturation of the lab [V].
V_SAT = 6.0


@dataclass
class Value:
    """One number of the report: value [unit], what it is, which part found it, and the
    true value when the data are synthetic (None otherwise)."""

    key: str
    value: float | None
    unit: str
    label: str
    part: str
    true: float | None = None

    def as_json(self) -> dict:
        out = {
            "value": _plain(self.value),
            "unit": self.unit,
            "label": self.label,
            "part": self.part,
        }
        if self.true is not None:
            out["true"] = self.true
            out["relative_error"] = _plain(relative_error(self.value, self.true))
        return out


def relative_error(value, true):
    if value is None or true is None or true == 0 or not math.isfinite(value):
        return None
    return abs(value - true) / abs(true)


def _plain(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")


@dataclass
class Lab:
    """The state of one report being written.

    out: the report folder; inputs: the recordings found; doc: the report; values: every number
    (key -> :class:`Value`) in the order found; results: the results.json document by part;
    B_eq [kg/s], f_c [N]: the best-known model, with where each came from.
    """

    out: Path
    inputs: Inputs
    doc: Document
    stream: object = None
    values: dict = field(default_factory=dict)
    results: dict = field(default_factory=dict)
    B_eq: float = HANDOUT_B_EQ
    B_eq_source: str = "the handout's estimate"
    B_eq_stderr: float | None = None  # [kg/s], when B_eq was fitted
    f_c: float = 0.0
    f_c_source: str = "none yet (the handout's model)"
    tuned: object = None  # tuning.design.tune.TuneResult of the pre-lab
    base: Plant | None = None  # the --plant model (its effects carry through), or None
    started: float = field(default_factory=time.perf_counter)
    figures: list = field(default_factory=list)
    diagnosis: bool = True  # the report has the diagnosis section

    # -------------------------------------------------------------- progress

    def say(self, text: str) -> None:
        """A progress line on stderr with the elapsed time."""
        stream = self.stream if self.stream is not None else sys.stderr
        print(f"lab [{time.perf_counter() - self.started:6.1f} s] {text}", file=stream, flush=True)

    # -------------------------------------------------------------- numbers

    def value(self, key, value, unit, label, part, *, true_key=None) -> float | None:
        """Record a number for the summary and results.json; returns it."""
        true = None
        synthetic = self.inputs.synthetic
        if synthetic is not None and true_key is not None and true_key in synthetic:
            true = float(synthetic[true_key])
        self.values[key] = Value(
            key, None if value is None else float(value), unit, label, part, true
        )
        return value

    # -------------------------------------------------------------- figures

    def figure_path(self, name: str) -> tuple[Path, str]:
        """(absolute path, path relative to the report) of figure ``name``.png."""
        rel = f"figures/{name}.png"
        self.figures.append(rel)
        return self.out / rel, rel

    # -------------------------------------------------------------- the model

    def plant(self, *, saturation: bool = True, coulomb: bool = True, **overrides) -> Plant:
        """The best-known cart (motor connected): appendix values, B_eq and f_c found so far,
        and the lab's 6 V limit as an amplifier saturation (the handout's Simulink block, so
        that recordings whose files name no software limit are simulated as they ran);
        without the effects the flags turn off. Built by :func:`jaxcart.build_plant`."""
        values = {"B_eq": self.B_eq}
        if saturation and (self.base is None or self.base.effect("saturation") is None):
            values["v_sat"] = V_SAT
        if coulomb and self.f_c > 0:
            values["f_c"] = self.f_c
        if self.base is not None:
            plant = self.base
            if not coulomb and plant.effect("coulomb") is not None:
                plant = dataclasses.replace(
                    plant, effects=tuple(e for e in plant.effects if type(e).name != "coulomb")
                )
            return with_values(plant, {**values, **overrides}, where="the lab's plant")
        return build_plant({**values, **overrides}, where="the lab's plant")

    def recording(self, slot):
        return self.inputs.recordings.get(slot)

    @property
    def synthetic(self) -> bool:
        return self.inputs.synthetic is not None


def fmt(x, digits: int = 4) -> str:
    """A number for the report: ``digits`` significant digits; None -> "n/a"."""
    if x is None:
        return "n/a"
    x = float(x)
    if math.isinf(x):
        return "∞" if x > 0 else "-∞"
    if math.isnan(x):
        return "n/a"
    if x != 0 and (abs(x) < 1e-3 or abs(x) >= 1e5):
        return f"{x:.{digits - 1}e}"
    return f"{x:.{digits}g}"


def mm(x, digits: int = 3) -> str:
    """A length [m] written in mm."""
    return "n/a" if x is None else f"{fmt(float(x) * 1e3, digits)} mm"
