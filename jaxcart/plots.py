"""Figures shared by every command: position and voltage against time, recorded runs against
simulations, saved as PNG, SVG or PDF (from the path's suffix; :data:`FORMATS`).

Roles set the style, so a figure reads the same everywhere: "experiment" is the measured run (a
wide light-grey line drawn beneath, so that a model that matches it shows as a coloured line
inside a grey band, never hidden by markers), "simulation" runs are coloured with distinct dash
styles, and "reference" is a thin black dashed line (position panel only); the settling band is
a shaded strip, the voltage limits dotted red. One legend for the figure sits below the axes,
off the data.

>>> import numpy as np
>>> t = np.linspace(0.0, 1.0, 101)
>>> plot_runs([Run("model", t, 0.5 * (1 - np.exp(-5 * t)))], title="demo",
...           path="/tmp/jaxcart-demo.png", voltage=False).name
'jaxcart-demo.png'
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from itertools import cycle
from pathlib import Path

import numpy as np

from hw.atomicio import save_figure
from jaxcart.errors import UserError

# matplotlib is imported where a figure is made (about 1 s, measured on 2 cores; matplotlib.figure
# 0.3-0.6 s by python -X importtime after this module): this module is imported while the command
# line's parser is built (add_format_option).

ROLES = ("experiment", "simulation", "reference")
DPI = 130
#: Figure formats every command can write (matplotlib writers), chosen by ``--format``.
FORMATS = ("png", "svg", "pdf")
#: The measured run: wide and light, beneath the models.
EXPERIMENT_STYLE = {"color": "0.62", "lw": 3.2, "ls": "-", "solid_capstyle": "butt", "zorder": 2}
#: The reference: thin, black, dashed, beneath everything.
REFERENCE_STYLE = {"color": "black", "lw": 0.9, "ls": (0, (5, 3)), "zorder": 1}
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


def preload() -> threading.Thread:
    """Import matplotlib's figure and PNG writer in a background thread, so that a command
    which plots at its end finds them loaded: the import (about half a second) overlaps the
    computation, which runs in XLA outside the interpreter lock. Returns the thread (the
    command joins it before it returns)."""

    def work():
        try:
            # lazy: this thread's point (matplotlib.figure: 0.3-0.6 s, python -X importtime)
            import matplotlib.backends.backend_agg  # noqa: F401
            import matplotlib.figure  # noqa: F401
        except Exception:  # the plotting call reports any real problem itself
            pass

    # Not a daemon: an exit mid-import waits for it (killed there, matplotlib's font-cache
    # lock file could be left behind).
    thread = threading.Thread(target=work, name="matplotlib-preload")
    thread.start()
    return thread


def plot_runs(
    runs,
    *,
    title: str,
    path,
    voltage: bool = True,
    v_limit: float | None = None,
    band: float | None = None,
    dpi: int = DPI,
    zoom: bool = False,
) -> Path:
    """Plot runs on position (and voltage) panels sharing the time axis; save at ``path``.

    runs: :class:`Run` objects (or anything with label, time, position, voltage, role).
    voltage: add the voltage panel when any run has a voltage. v_limit: draw +/- v_limit [V].
    band: shade the settling band, +/- ``band`` (a fraction, 0.02 for 2 %) of the step around
    the reference's final value; the step runs from the first non-reference run's start.
    zoom: an inset of the error r − y [mm] of every run over the second half of the time after
    the reference's last change, where a steady-state error of millimetres is visible.
    path: the file (its suffix sets the format: .png, .svg, .pdf), or several paths, each
    written. Uses matplotlib's object API (no pyplot state). Returns the (first) path.
    """
    fig = runs_figure(runs, title=title, voltage=voltage, v_limit=v_limit, band=band, zoom=zoom)
    return save(fig, path, dpi=dpi)


def runs_figure(runs, *, title: str, voltage=True, v_limit=None, band=None, zoom=False):
    """The :class:`matplotlib.figure.Figure` that :func:`plot_runs` saves (same arguments)."""
    # lazy: matplotlib.figure costs 0.3-0.6 s at start-up (python -X importtime; note at the top)
    from matplotlib.figure import Figure

    runs = list(runs)
    with_voltage = voltage and any(getattr(r, "voltage", None) is not None for r in runs)
    fig = Figure(figsize=(8.0, 6.0 if with_voltage else 4.2), layout="constrained")
    if with_voltage:
        ax_y, ax_v = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    else:
        ax_y, ax_v = fig.subplots(1, 1), None
    styles = cycle(zip(_COLORS, cycle(_DASHES)))
    drawn = []
    for run in runs:
        role = getattr(run, "role", "simulation")
        t = np.asarray(run.time, dtype=float)
        style = _style(role, t.size, styles)
        ax_y.plot(t, np.asarray(run.position, dtype=float), label=run.label, **style)
        drawn.append((run, style))
        v = getattr(run, "voltage", None)
        if ax_v is not None and v is not None and role != "reference":
            ax_v.plot(t, np.asarray(v, dtype=float), label=run.label, **style)
    if band:
        _settling_band(ax_y, runs, band)
    ax_y.set_ylabel("position y [m]")
    ax_y.set_title(title)
    if zoom:
        _error_inset(ax_y, drawn)
    last = ax_y
    if ax_v is not None:
        if v_limit is not None and np.isfinite(v_limit):
            for sign in (1, -1):
                ax_v.axhline(
                    sign * v_limit,
                    color="tab:red",
                    lw=0.9,
                    ls=":",
                    label=f"±{v_limit:g} V limit" if sign > 0 else None,
                )
        ax_v.set_ylabel("voltage [V]")
        last = ax_v
    last.set_xlabel("time t [s]")
    for ax in (ax_y, ax_v):
        if ax is not None:
            ax.grid(True, alpha=0.3)
    figure_legend(fig, [ax_y] + ([ax_v] if ax_v is not None else []))
    return fig


def figure_legend(fig, axes, *, ncols: int = 2, fontsize="small") -> None:
    """One legend for the whole figure below its axes (off the data), each label once."""
    handles, labels = [], []
    for ax in axes:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=ncols, fontsize=fontsize)


def save(fig, path, *, dpi: int = DPI) -> Path:
    """Write ``fig`` to ``path`` (or to each of several paths), the format from the suffix
    (:data:`FORMATS`); folders are made. Returns the first path."""
    paths = [Path(path)] if isinstance(path, (str, Path)) else [Path(p) for p in path]
    for p in paths:
        save_figure(fig, p, dpi=dpi)  # a temporary name, then renamed: never half a file
    return paths[0]


def with_format(path, fmt: str | None) -> Path:
    """``path`` with the suffix of ``fmt`` ("png", "svg", "pdf"); None keeps the path."""
    if fmt is None:
        return Path(path)
    if fmt not in FORMATS:
        raise ValueError(f"figure format {fmt!r}: use one of {', '.join(FORMATS)}")
    return Path(path).with_suffix("." + fmt)


def add_format_option(parser) -> None:
    """The ``--format png|svg|pdf`` option of a command that draws figures (``args.format``,
    None when not given)."""
    parser.add_argument(
        "--format",
        choices=FORMATS,
        default=None,
        help="figure format: png (default), svg or pdf (vector, for a LaTeX report)",
    )


def figure_name(path, fmt: str | None, *, option: str = "--plot") -> Path:
    """A figure's path under ``--format``: ``path`` with the suffix of ``fmt``, where ``path``
    has no figure suffix of its own; a path whose suffix names another format is refused
    (one line naming both), and without ``fmt`` the path is kept."""
    path = Path(path)
    if fmt is None:
        return path
    suffix = path.suffix.lower().lstrip(".")
    if suffix in FORMATS and suffix != fmt:
        raise UserError(
            f"{option} {path} is a .{suffix} file but --format is {fmt}; name it "
            f"{path.with_suffix('.' + fmt).name} or leave out one of the two"
        )
    return with_format(path, fmt)


def _error_inset(ax, drawn) -> None:
    """The error r − y [mm] of each run after the reference settled, in an inset."""
    ref = next((r for r, _ in drawn if getattr(r, "role", None) == "reference"), None)
    if ref is None or np.size(ref.position) < 2:
        return
    t_ref, r = np.asarray(ref.time, dtype=float), np.asarray(ref.position, dtype=float)
    changed = np.flatnonzero(np.abs(np.diff(r)) > 0)
    t_change = t_ref[changed[-1] + 1] if changed.size else t_ref[0]
    if t_ref[-1] - t_change < 0.25 * (t_ref[-1] - t_ref[0]):
        return  # a reference that keeps moving (a sine, a ramp) has no steady state to zoom on
    t0 = t_change + 0.5 * (t_ref[-1] - t_change)
    target, start = float(r[-1]), float(r[0])
    # Below the final value for a step up (where the curves are not), above for a step down.
    box = (0.5, 0.08, 0.47, 0.42) if target >= start else (0.5, 0.5, 0.47, 0.42)
    inset = ax.inset_axes(box)
    top = 0.0
    for run, style in drawn:
        if getattr(run, "role", None) == "reference":
            continue
        t = np.asarray(run.time, dtype=float)
        keep = t >= t0
        if not keep.any():
            continue
        e = (target - np.asarray(run.position, dtype=float)[keep]) * 1e3
        inset.plot(t[keep], e, label=run.label, **style)
        top = max(top, float(np.max(np.abs(e))))
    inset.axhline(0.0, **REFERENCE_STYLE)
    span = max(1.25 * top, 0.05)
    inset.set_ylim(-span, span)
    inset.set_xlim(t0, t_ref[-1])
    inset.set_title("steady-state error r − y [mm], zoomed", fontsize="x-small")
    inset.tick_params(labelsize="x-small")
    inset.grid(True, alpha=0.3)
    inset.set_facecolor("white")


def _settling_band(ax, runs, band: float) -> None:
    ref = next((r for r in runs if getattr(r, "role", None) == "reference"), None)
    moved = next((r for r in runs if getattr(r, "role", None) != "reference"), None)
    if ref is None or moved is None or np.size(ref.position) == 0:
        return
    target = float(np.asarray(ref.position, dtype=float)[-1])
    width = band * abs(target - float(np.asarray(moved.position, dtype=float)[0]))
    if width > 0:
        ax.axhspan(
            target - width,
            target + width,
            color="tab:green",
            alpha=0.18,
            lw=0,
            zorder=0,
            label=f"±{band * 100:g} % settling band",
        )


def _style(role, n, styles) -> dict:
    if role == "experiment":
        return dict(EXPERIMENT_STYLE)
    if role == "reference":
        return dict(REFERENCE_STYLE)
    color, dash = next(styles)
    return dict(color=color, lw=1.6, ls=dash, zorder=3)
