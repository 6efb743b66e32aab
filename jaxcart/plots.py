"""Figures shared by every command: position and voltage against time, recorded runs against
simulations, saved as PNG.

Roles set the style, so a figure reads the same everywhere: "experiment" is the measured run
(solid black with open markers), "simulation" runs are coloured with distinct dash styles, and
"reference" is a thin grey dashed line (position panel only).

>>> import numpy as np
>>> t = np.linspace(0.0, 1.0, 101)
>>> plot_runs([Run("model", t, 0.5 * (1 - np.exp(-5 * t)))], title="demo",
...           path="/tmp/jaxcart-demo.png", voltage=False).name
'jaxcart-demo.png'
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import cycle
from pathlib import Path

import numpy as np

ROLES = ("experiment", "simulation", "reference")
DPI = 130
_DASHES = ("-", "--", "-.", ":")
_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


@dataclass(frozen=True, eq=False)
class Run:
    """One curve set: time [s], position [m], optional voltage [V], a legend label and a role
    ("experiment", "simulation" or "reference")."""

    label: str
    time: np.ndarray
    position: np.ndarray
    voltage: np.ndarray | None = None
    role: str = "simulation"

    def __post_init__(self):
        if self.role not in ROLES:
            raise ValueError(f"role {self.role!r}: use one of {', '.join(ROLES)}")


def run_from_response(response, label: str, role: str = "simulation") -> Run:
    """A :class:`jaxcart.Response` as a run; its voltage is the command the software sent [V]."""
    return Run(
        label,
        np.asarray(response.time),
        np.asarray(response.position),
        np.asarray(response.command),
        role,
    )


def run_from_recording(recording, label: str | None = None) -> Run:
    """A :class:`jaxcart.files.Recording` as the experiment run (voltage: column v, if any)."""
    return Run(
        label or f"recorded ({recording.path.name})",
        recording.time,
        recording.position,
        recording.command,
        "experiment",
    )


def reference_run(time, reference, label: str = "reference r") -> Run:
    """The reference r [m] as a thin grey dashed line."""
    return Run(label, np.asarray(time), np.asarray(reference), None, "reference")


def preload() -> None:
    """Import matplotlib's figure and PNG writer in a background thread, so that a command
    which plots at its end finds them loaded: the import (about half a second) overlaps the
    computation, which runs in XLA outside the interpreter lock."""
    import threading

    def work():
        try:
            import matplotlib.backends.backend_agg  # noqa: F401
            import matplotlib.figure  # noqa: F401
        except Exception:  # the plotting call reports any real problem itself
            pass

    # Not a daemon: an exit mid-import waits for it (killed there, matplotlib's font-cache
    # lock file could be left behind).
    threading.Thread(target=work, name="matplotlib-preload").start()


def plot_runs(
    runs,
    *,
    title: str,
    path,
    voltage: bool = True,
    v_limit: float | None = None,
    band: float | None = None,
    dpi: int = DPI,
) -> Path:
    """Plot runs on position (and voltage) panels sharing the time axis; save a PNG at ``path``.

    runs: :class:`Run` objects (or anything with label, time, position, voltage, role).
    voltage: add the voltage panel when any run has a voltage. v_limit: draw +/- v_limit [V].
    band: draw the settling band, +/- ``band`` (a fraction, 0.02 for 2 %) of the step around
    the reference's final value, dotted (the reference itself is dashed); the step runs from
    the first non-reference run's start. Uses matplotlib's object API (no pyplot state).
    Returns the path written.
    """
    from matplotlib.figure import Figure

    runs = list(runs)
    with_voltage = voltage and any(getattr(r, "voltage", None) is not None for r in runs)
    fig = Figure(figsize=(8.0, 6.0 if with_voltage else 4.2), layout="constrained")
    if with_voltage:
        ax_y, ax_v = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    else:
        ax_y, ax_v = fig.subplots(1, 1), None
    styles = cycle(zip(_COLORS, cycle(_DASHES)))
    for run in runs:
        role = getattr(run, "role", "simulation")
        t = np.asarray(run.time, dtype=float)
        style = _style(role, t.size, styles)
        ax_y.plot(t, np.asarray(run.position, dtype=float), label=run.label, **style)
        v = getattr(run, "voltage", None)
        if ax_v is not None and v is not None and role != "reference":
            ax_v.plot(t, np.asarray(v, dtype=float), label=run.label, **style)
    if band:
        _settling_band(ax_y, runs, band)
    ax_y.set_ylabel("position y [m]")
    ax_y.set_title(title)
    ax_y.legend(loc="best", fontsize="small")
    last = ax_y
    if ax_v is not None:
        if v_limit is not None and np.isfinite(v_limit):
            for sign in (1, -1):
                ax_v.axhline(
                    sign * v_limit,
                    color="tab:red",
                    lw=0.8,
                    ls=":",
                    label=f"±{v_limit:g} V limit" if sign > 0 else None,
                )
            ax_v.legend(loc="best", fontsize="small")
        ax_v.set_ylabel("voltage [V]")
        last = ax_v
    last.set_xlabel("time t [s]")
    for ax in (ax_y, ax_v):
        if ax is not None:
            ax.grid(True, alpha=0.3)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def _settling_band(ax, runs, band: float) -> None:
    ref = next((r for r in runs if getattr(r, "role", None) == "reference"), None)
    moved = next((r for r in runs if getattr(r, "role", None) != "reference"), None)
    if ref is None or moved is None or np.size(ref.position) == 0:
        return
    target = float(np.asarray(ref.position, dtype=float)[-1])
    width = band * abs(target - float(np.asarray(moved.position, dtype=float)[0]))
    if width > 0:
        for sign in (1, -1):
            ax.axhline(
                target + sign * width,
                color="0.35",
                lw=0.8,
                ls=":",
                zorder=1,
                label=f"±{band * 100:g} % settling band" if sign > 0 else None,
            )


def _style(role, n, styles) -> dict:
    if role == "experiment":
        return dict(
            color="black",
            lw=1.0,
            ls="-",
            marker="o",
            ms=3.5,
            fillstyle="none",
            markevery=max(1, n // 40),
            zorder=2,
        )
    if role == "reference":
        return dict(color="0.55", lw=0.9, ls="--", zorder=1)
    color, dash = next(styles)
    return dict(color=color, lw=1.6, ls=dash, zorder=3)
