"""Predictions drawn: each design's step on the cart as measured, one panel each, side by side.

A panel shows the band the step lies in (:class:`tuning.design.prediction.Prediction`: the
level's share of the drawn carts, shaded), the fitted cart's step (a line), the reference and
the 2 % settling band about it, the spec's settling bound (a dotted vertical line) and, where
there is one, the measured run of that design (the wide grey line of
:data:`jaxcart.plots.EXPERIMENT_STYLE`). The panels share their axes, so the designs compare at
a glance; one legend for the figure sits below them.

>>> import jaxcart as jc  # doctest: +SKIP
>>> plot_predictions([Panel("design", prediction)], "/tmp/band.png")  # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure

from jaxcart.metrics import SETTLING_BAND
from jaxcart.plots import EXPERIMENT_STYLE, REFERENCE_STYLE, figure_legend, save

#: The band's and the fitted cart's colours.
BAND_COLOR, LINE_COLOR = "tab:blue", "tab:blue"


@dataclass(frozen=True, eq=False)
class Panel:
    """One panel: its title, the design's prediction and the measured run ((time [s],
    position [m]) or None)."""

    title: str
    prediction: object
    measured: tuple | None = None


def plot_predictions(panels, path, *, title: str | None = None, zoom: bool = True):
    """Draw ``panels`` (:class:`Panel`) side by side and save the figure at ``path`` (its
    suffix sets the format); ``zoom``: the position axis spans the last 20 % of the step and
    its overshoot, the time axis twice the spec's settling bound, where settling and overshoot
    show. Returns the path."""
    panels = list(panels)
    fig = Figure(figsize=(4.0 * len(panels) + 1.0, 4.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(panels), sharex=True, sharey=True))
    for ax, panel in zip(axes, panels, strict=True):
        _panel(ax, panel)
    if zoom:
        _zoom(axes[0], [p.prediction for p in panels], panels)
    axes[0].set_ylabel("position y [m]")
    if title:
        fig.suptitle(title)
    figure_legend(fig, list(axes), ncols=3)
    return save(fig, path)


def _panel(ax, panel: Panel) -> None:
    p = panel.prediction
    t = np.asarray(p.time, dtype=float)
    lo, hi = p.position_band()
    ax.fill_between(
        t,
        lo,
        hi,
        color=BAND_COLOR,
        alpha=0.25,
        lw=0,
        label=_band_label(p),
        zorder=2,
    )
    if panel.measured is not None:
        tm, ym = (np.asarray(x, dtype=float) for x in panel.measured)
        ax.plot(tm, ym, label="measured run", **EXPERIMENT_STYLE)
    ax.plot(t, p.nominal_position, color=LINE_COLOR, lw=1.4, label="the fitted cart", zorder=3)
    ax.plot(t, p.reference, label="reference r", **REFERENCE_STYLE)
    target = float(p.reference[-1])
    width = SETTLING_BAND * abs(target - float(p.nominal_position[0]))
    ax.axhspan(target - width, target + width, color="tab:green", alpha=0.15, lw=0, zorder=0,
               label=f"±{SETTLING_BAND * 100:g} % settling band")  # fmt: skip
    ax.axvline(p.spec.settling_time, color="tab:red", lw=0.9, ls=":", label="settling bound")
    lo_s, hi_s = p.interval("settling_time")
    ax.set_title(
        f"{panel.title}\nsettling {_s(p.nominal['settling_time'])} [{_s(lo_s)}, {_s(hi_s)}] s, "
        f"P(spec) {p.p_meet:.0%}",
        fontsize="small",
    )
    ax.set_xlabel("time t [s]")
    ax.grid(True, alpha=0.3)


def _band_label(p) -> str:
    """The band's legend entry: its level and what it holds."""
    miss = float(p.model_error.get("settling_time", 0.0))
    text = f"{p.level:.0%} band, {p.n} carts drawn from the fit"
    return text + (f", ±{miss * 1e3:.0f} ms the model's miss" if miss > 0 else "")


def _s(x) -> str:
    return f"{x:.3f}" if np.isfinite(x) else "never"


def _zoom(ax, predictions, panels) -> None:
    """The position axis from 80 % of the step to past the farthest band, the time axis to
    twice the settling bound (the axes are shared)."""
    target = float(predictions[0].reference[-1])
    start = float(predictions[0].nominal_position[0])
    step = target - start
    sign = 1.0 if step >= 0 else -1.0
    far = max(
        sign * float(np.max(sign * p.position_band()[1 if sign > 0 else 0])) for p in predictions
    )
    for panel in panels:
        if panel.measured is not None:
            far = max(far, sign * float(np.max(sign * np.asarray(panel.measured[1]))))
    ends = (start + 0.8 * step, sign * far + 0.03 * step)
    ax.set_ylim(min(ends), max(ends))
    spec = predictions[0].spec
    ax.set_xlim(0.0, min(2.0 * spec.settling_time, max(float(p.time[-1]) for p in predictions)))
