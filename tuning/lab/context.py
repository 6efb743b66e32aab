"""What the lab report's rendering shares: the report being written (:class:`Lab`: its folder,
document, figure format and progress line), the numbers of the summary (:class:`Value`) and how
numbers are written (:func:`fmt`, :func:`mm`).

Nothing computed travels through :class:`Lab`: each part is a function of its inputs that
returns a frozen result (:mod:`tuning.lab.part_i` ... :mod:`tuning.lab.part_v`); the report
(:mod:`tuning.lab.report`) hands results to the parts that need them and renders each.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from jaxcart.errors import UserError
from tuning.lab.html import Document
from tuning.lab.inputs import Inputs

#: The handout's estimate of B_eq [kg/s], used until a recording says otherwise.
HANDOUT_B_EQ = 5.4
#: Amplifier saturation of the lab [V].
V_SAT = 6.0
#: Figure formats the report can write (matplotlib's writers for them).
FIGURE_FORMATS = ("png", "svg", "pdf")


@dataclass(frozen=True)
class Value:
    """One number of the report's summary: value [unit], what it is, which part found it, the
    key of its true value among the synthetic data's parameters (None: no truth), and whether
    it only bounds that quantity ("lower" or "upper"; None: an estimate of it)."""

    key: str
    value: float | None
    unit: str
    label: str
    part: str
    true_key: str | None = None
    bound: str | None = None

    def true(self, synthetic: dict | None) -> float | None:
        """The true value [unit] when the data are synthetic and know it, else None."""
        if synthetic is None or self.true_key is None or self.true_key not in synthetic:
            return None
        return float(synthetic[self.true_key])

    def to_json(self, synthetic: dict | None = None) -> dict:
        out = {
            "value": _plain(self.value),
            "unit": self.unit,
            "label": self.label,
            "part": self.part,
        }
        if self.bound is not None:  # a class judges outliers on estimates only
            out["bound"] = self.bound
        true = self.true(synthetic)
        if true is not None:
            out["true"] = true
            out["relative_error"] = _plain(relative_error(self.value, true))
        return out


def value(key, x, unit, label, part, *, true_key=None, bound=None) -> Value:
    """A :class:`Value` with ``x`` as a float (None stays None)."""
    return Value(key, None if x is None else float(x), unit, label, part, true_key, bound)


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
    """The report being written (rendering only; no part reads what another left here).

    out: the report folder; inputs: the recordings found; doc: the report; fmt: the figures'
    format ("png", "svg" or "pdf"); diagnosis: whether the report has the diagnosis section;
    results: the results.json document, assembled by the report; gains: the PID written to
    gains.json (with ``gains_metrics`` and ``gains_extra``: its prediction and margins, which
    ``jaxcart run`` checks a run against), or None; figures: every figure written, relative
    paths.
    """

    out: Path
    inputs: Inputs
    doc: Document
    stream: object = None
    started: float = field(default_factory=time.perf_counter)
    fmt: str = "png"
    diagnosis: bool = True
    results: dict = field(default_factory=dict)
    gains: object = None
    gains_metrics: dict = field(default_factory=dict)
    gains_source: str = "jaxcart lab: pre-lab design (handout model)"
    gains_extra: dict = field(default_factory=dict)
    figures: list = field(default_factory=list)

    def say(self, text: str) -> None:
        """A progress line on stderr with the elapsed time."""
        stream = self.stream if self.stream is not None else sys.stderr
        print(f"lab [{time.perf_counter() - self.started:6.1f} s] {text}", file=stream, flush=True)

    def figure_path(self, name: str) -> tuple:
        """(where to save, path relative to the report) of figure ``name`` in the format.
        Where to save is one path, or for PDF two: the PDF and the PNG that report.html
        embeds (a browser shows no PDF inside a page)."""
        rel = f"figures/{name}.{self.fmt}"
        self.figures.append(rel)
        if self.fmt == "pdf":
            return (self.out / rel, self.out / f"figures/{name}.png"), rel
        return self.out / rel, rel

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


def check_format(fmt_name: str) -> str:
    """``fmt_name`` lower-cased if it is one of :data:`FIGURE_FORMATS`; else a one-line error."""
    name = str(fmt_name).lower().lstrip(".")
    if name not in FIGURE_FORMATS:
        raise UserError(
            f"--format {fmt_name}: not a figure format the report writes; use one of "
            f"{', '.join(FIGURE_FORMATS)}"
        )
    return name
