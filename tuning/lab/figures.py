"""The lab report's figures: one per handout item, axes labelled with units, the experiment
drawn as a wide light-grey line beneath the models (a model that matches shows as a coloured
line inside the grey band; no markers to hide it), each simulation with its own colour and
dashes, one legend below the axes.

Each function draws, saves ``path`` (its suffix sets the format, PNG, SVG or PDF; several paths
write one file each, :func:`jaxcart.plots.save`), with matplotlib's object API: no pyplot
figure is left open and no backend is switched for the process.
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np
from matplotlib.figure import Figure

from jaxcart.plots import figure_legend, save

DPI = 110
SIZE = (7.5, 5.0)
#: Line styles of the simulations, in the order they are given (the experiment is solid black).
STYLES = (
    {"color": "tab:blue", "linestyle": "--"},
    {"color": "tab:red", "linestyle": "-."},
    {"color": "tab:green", "linestyle": ":"},
    {"color": "tab:purple", "linestyle": (0, (5, 2, 1, 2, 1, 2))},
)
#: The experiment's style, as in jaxcart.plots: wide, light grey, beneath the models.
EXPERIMENT = {
    "color": "0.62",
    "linestyle": "-",
    "linewidth": 3.2,
    "solid_capstyle": "butt",
    "zorder": 2,
}


@dataclass(frozen=True)
class Trace:
    """One line: time [s], values (in the axis' unit), legend label; ``measured`` draws it as
    the experiment (solid black)."""

    time: np.ndarray
    values: np.ndarray
    label: str
    measured: bool = False


def _draw(ax, traces):
    k = 0
    for trace in traces:
        if trace.measured:
            style = EXPERIMENT
        else:
            style = {"linewidth": 1.6, "zorder": 3, **STYLES[k % len(STYLES)]}
            k += 1
        ax.plot(np.asarray(trace.time), np.asarray(trace.values), label=trace.label, **style)


def _save(fig, path, axes=None):
    """Save (the legend of ``axes`` below them, if given)."""
    if axes is not None:
        figure_legend(fig, axes, ncols=1 if len(axes) == 1 else 2, fontsize=8.5)
    return save(fig, path, dpi=DPI)


def time_plot(path, traces, *, ylabel, title, hlines=(), xlim=None, ylim=None, zoom=None):
    """Signals against time on one axis. ``hlines``: (value, label, style dict) references.
    zoom: (t0 [s], title) for an inset, upper right, of the traces from t0 on (where the
    answer, a final error of millimetres, is small beside the start)."""
    fig = Figure(figsize=SIZE, layout="constrained")
    ax = fig.subplots()
    _draw(ax, traces)
    if zoom is not None:
        _inset(ax, traces, hlines, *zoom)
    for value, label, style in hlines:
        ax.axhline(value, label=label, **{"color": "0.45", "linewidth": 1.0, **style})
    ax.set_xlabel("time t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if xlim is not None:
        ax.set_xlim(*xlim)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.grid(True, alpha=0.3)
    return _save(fig, path, [ax])


def _inset(ax, traces, hlines, t0: float, title: str) -> None:
    inset = ax.inset_axes((0.5, 0.5, 0.47, 0.4))
    _draw(inset, traces)
    low, high = np.inf, -np.inf
    for trace in traces:
        t, v = np.asarray(trace.time), np.asarray(trace.values)
        if np.any(t >= t0):
            low, high = min(low, v[t >= t0].min()), max(high, v[t >= t0].max())
    for value, _, style in hlines:
        inset.axhline(value, **{"color": "0.45", "linewidth": 1.0, **style})
    if np.isfinite(low):
        pad = max(0.15 * (high - low), 0.05 * max(abs(low), abs(high)), 0.05)
        inset.set_ylim(low - pad, high + pad)
    inset.set_xlim(t0, max(float(np.asarray(tr.time)[-1]) for tr in traces))
    inset.set_title(title, fontsize="x-small")
    inset.tick_params(labelsize="x-small")
    inset.grid(True, alpha=0.3)


def two_panel(
    path,
    top,
    bottom,
    *,
    top_ylabel,
    bottom_ylabel,
    title,
    xlim=None,
    top_hlines=(),
    bottom_hlines=(),
):
    """Two signals against the same time axis (e.g. position above, voltage below)."""
    fig = Figure(figsize=(7.5, 6.2), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    for ax, traces, lines, label in (
        (ax1, top, top_hlines, top_ylabel),
        (ax2, bottom, bottom_hlines, bottom_ylabel),
    ):
        _draw(ax, traces)
        for value, text, style in lines:
            ax.axhline(value, label=text, **{"color": "0.45", "linewidth": 1.0, **style})
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    ax2.set_xlabel("time t [s]")
    if xlim is not None:
        ax2.set_xlim(*xlim)
    ax1.set_title(title)
    return _save(fig, path, [ax1, ax2])


def root_locus(path, rldata, *, ki_bound, omega, title):
    """Root locus (python-control's plot) with the imaginary-axis crossing marked."""
    fig = Figure(figsize=(7.0, 5.6), layout="constrained")
    ax = fig.subplots()
    cplt = control.root_locus_plot(rldata, ax=ax, legend_loc=False)
    poles_line, _, loci = cplt.lines[0]
    for line in poles_line:
        line.set_label("open-loop poles of H (k_i = 0)")
    for i, line in enumerate(loci):
        line.set_label(
            f"closed-loop poles, k_i = 0 to {rldata.gains[-1]:.0f}" if i == 0 else "_nolegend_"
        )
    ax.plot(
        [0.0, 0.0],
        [omega, -omega],
        "o",
        markersize=9,
        markerfacecolor="none",
        markeredgecolor="tab:red",
        markeredgewidth=2.0,
        linestyle="none",
        label=f"imaginary-axis crossing: k_i = {ki_bound:.2f} V/(m s), s = ±j {omega:.3f} rad/s",
    )
    ax.axvline(0.0, color="0.3", linewidth=0.8)
    left = float(np.min(np.asarray(rldata.poles).real))
    ax.set_xlim(min(left * 1.25, -2.0 * omega), 1.0 * omega)
    ax.set_ylim(-2.2 * omega, 2.2 * omega)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("real part Re(s) [1/s]")
    ax.set_ylabel("imaginary part Im(s) [rad/s]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize=8.5)
    return _save(fig, path)
