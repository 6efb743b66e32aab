"""The lab report's figures: one PNG per handout item, axes labelled with units, the
experiment drawn solid black and each simulation with its own line style, all in the legend.

Each function draws, saves ``path`` (PNG) and closes its figure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DPI = 110
SIZE = (7.5, 4.2)
#: Line styles of the simulations, in the order they are given (the experiment is solid black).
STYLES = (
    {"color": "tab:blue", "linestyle": "--"},
    {"color": "tab:red", "linestyle": "-."},
    {"color": "tab:green", "linestyle": ":"},
    {"color": "tab:purple", "linestyle": (0, (5, 2, 1, 2, 1, 2))},
)
#: The experiment's style, as in jaxcart.plots: solid black with open markers.
EXPERIMENT = {
    "color": "black",
    "linestyle": "-",
    "linewidth": 1.0,
    "marker": "o",
    "markersize": 3.5,
    "fillstyle": "none",
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


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _draw(ax, traces):
    k = 0
    for trace in traces:
        if trace.measured:
            style = {**EXPERIMENT, "markevery": max(1, np.size(trace.time) // 40)}
        else:
            style = {"linewidth": 1.6, "zorder": 3, **STYLES[k % len(STYLES)]}
            k += 1
        ax.plot(np.asarray(trace.time), np.asarray(trace.values), label=trace.label, **style)


def _save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    _pyplot().close(fig)
    return path


def time_plot(path, traces, *, ylabel, title, hlines=(), xlim=None, ylim=None, legend="best"):
    """Signals against time on one axis. ``hlines``: (value, label, style dict) references."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=SIZE)
    _draw(ax, traces)
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
    ax.legend(loc=legend, fontsize=8.5)
    return _save(fig, path)


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
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7.5, 6.2), sharex=True)
    for ax, traces, lines, label in (
        (ax1, top, top_hlines, top_ylabel),
        (ax2, bottom, bottom_hlines, bottom_ylabel),
    ):
        _draw(ax, traces)
        for value, text, style in lines:
            ax.axhline(value, label=text, **{"color": "0.45", "linewidth": 1.0, **style})
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8.5)
    ax2.set_xlabel("time t [s]")
    if xlim is not None:
        ax2.set_xlim(*xlim)
    ax1.set_title(title)
    return _save(fig, path)


def root_locus(path, rldata, *, ki_bound, omega, title):
    """Root locus (python-control's plot) with the imaginary-axis crossing marked."""
    import control

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 5.6))
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
