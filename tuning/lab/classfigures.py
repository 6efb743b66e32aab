"""The class's figures (``jaxcart class``): the distribution of the handout's numbers over the
class, and every student's recordings overlaid, one panel per experiment.

Drawn from a :class:`tuning.lab.classroom.ClassResult` (nothing is computed here); PNG files
with matplotlib's object API (no pyplot state).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from jaxcart.plots import DPI
from tuning.lab.inputs import SLOTS

#: The numbers whose distributions are drawn, when the reports have them and they vary.
PREFERRED = (
    "B_eq_tap_fit",
    "B_eq_tap_handout",
    "B_eq_p50_coulomb",
    "f_c_ramp_fit",
    "f_c_ramp_handout",
    "e_inf_measured",
    "pi_rms",
    "pid_measured_settling_time",
    "pid_measured_overshoot",
    "pid_measured_steady_state_error",
)
#: Most panels of the distributions figure.
MAX_PANELS = 10
#: Most students named in the overlays' legend (more: no legend).
MAX_LEGEND = 40
#: The overlays' line styles: ten colours (tab10, told apart by most colour vision) times
#: four dash patterns tell 40 students apart; tab20's pairs of a dark and a light shade did
#: not tell 20 apart.
COLOURS = 10
DASHES = ("-", "--", ":", "-.")


def line_style(k: int) -> dict:
    """The colour and dash of the ``k``-th student's lines (matplotlib keywords): the first ten
    solid in tab10's colours, the next ten dashed in the same colours, and so on."""
    cmap = colormaps["tab10"]
    return {"color": cmap(k % COLOURS), "ls": DASHES[(k // COLOURS) % len(DASHES)]}


def draw(result, folder) -> list[tuple[Path, str]]:
    """Write the class's figures into ``folder``; returns [(path, caption)]."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    figures = []
    columns = _distribution_columns(result)
    if columns:
        path = distributions(result, columns, folder / "distributions.png")
        figures.append(
            (
                path,
                "The class's distribution of each number: one dot per student (complete labs), "
                "the box from the lower to the upper quartile with the median; flagged values "
                "are red and named; dotted red: the specification's bound.",
            )
        )
    if any(s.runs for s in result.students):
        path = overlays(result, folder / "overlays.png")
        figures.append(
            (
                path,
                "Every student's recordings overlaid, one panel per experiment of the handout "
                "(positions as recorded; a colour and a dash per student; flagged students "
                "drawn thicker and named; dotted black: the reference of closed-loop steps).",
            )
        )
    return figures


def _distribution_columns(result) -> list:
    varying = {c.key: c for c in result.varying()}
    chosen = [varying[k] for k in PREFERRED if k in varying]
    if not chosen:
        chosen = list(varying.values())
    return chosen[:MAX_PANELS]


def _scale(unit: str) -> tuple[float, str]:
    """Display scale: metres as millimetres (the errors are millimetres)."""
    return (1e3, "mm") if unit == "m" else (1.0, unit)


def distributions(result, columns, path) -> Path:
    """One strip per number: each complete student's value (jittered vertically), a box plot,
    flagged values in red with the student's name, the spec's bound where there is one."""
    n = len(columns)
    rows = (n + 1) // 2
    fig = Figure(figsize=(11.0, 1.9 * rows + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, 2 if n > 1 else 1)).ravel()
    bounds = {
        "pid_measured_settling_time": result.spec["settling_time"],
        "pid_measured_overshoot": result.spec["overshoot"],
    }
    for ax, column in zip(axes, columns, strict=False):
        _strip(ax, result, column, bounds.get(column.key))
    for ax in axes[n:]:
        ax.set_visible(False)
    done = sum(s.complete for s in result.students)
    fig.suptitle(f"jaxcart class: the numbers of {done} complete labs")
    fig.savefig(path, dpi=DPI)
    return Path(path)


def _strip(ax, result, column, bound) -> None:
    scale, unit = _scale(column.unit)
    named = [
        (s, v) for s in result.students if s.complete and (v := s.value(column.key)) is not None
    ]
    if not named:
        ax.set_visible(False)
        return
    values = np.array([v for _, v in named]) * scale
    _box(ax, values)
    jitter = np.random.default_rng(0).uniform(-0.25, 0.25, values.size)
    flagged = np.array([column.key in s.marked for s, _ in named], dtype=bool)
    ax.scatter(values[~flagged], jitter[~flagged], s=18, color="tab:blue", zorder=2)
    ax.scatter(values[flagged], jitter[flagged], s=30, color="tab:red", zorder=3, label="flagged")
    for (s, _), x, y, hot in zip(named, values, jitter, flagged, strict=True):
        if hot:
            ax.annotate(s.name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7)
    if bound is not None:
        ax.axvline(bound * scale, color="tab:red", ls=":", lw=1.0)
    ax.set_yticks([])
    ax.set_ylim(-0.5, 0.5)
    ax.set_title(
        f"Part ({column.part}) {column.label}"
        if column.part not in ("", "pre-lab")
        else column.label,
        fontsize=9,
    )
    ax.set_xlabel(f"[{unit}]" if unit else "", fontsize=8)
    ax.tick_params(labelsize=8)
    ax.grid(True, axis="x", alpha=0.3)


def _box(ax, values) -> None:
    """Quartile box, median and whiskers to the extremes, drawn by hand (matplotlib's boxplot
    changed its orientation argument between the versions jaxcart supports)."""
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    lo, hi = float(np.min(values)), float(np.max(values))
    ax.add_patch(Rectangle((q1, -0.3), q3 - q1, 0.6, fill=False, ec="0.3", lw=1.0, zorder=1))
    ax.vlines(median, -0.3, 0.3, color="tab:orange", lw=1.5, zorder=1)
    ax.hlines([0.0, 0.0], [lo, q3], [q1, hi], color="0.3", lw=1.0, zorder=1)
    ax.vlines([lo, hi], -0.12, 0.12, color="0.3", lw=1.0, zorder=1)


def overlays(result, path) -> Path:
    """A panel per experiment (slot): every complete student's recorded position against
    time, one colour and dash per student (:func:`line_style`), and the reference of
    closed-loop steps. A flagged student's runs are drawn thicker and named at their end: in a
    bundle of 20 runs no colour tells one apart, a name does."""
    slots = [s for s in SLOTS if any(s in st.runs for st in result.students)]
    cols = 3 if len(slots) > 4 else 2
    rows = (len(slots) + cols - 1) // cols
    fig = Figure(figsize=(4.2 * cols + 1.8, 3.0 * rows + 0.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    students = [s for s in result.students if s.runs]
    for ax, slot in zip(axes, slots, strict=False):
        drawn_ref = False
        ends = []
        for k, student in enumerate(students):
            if slot not in student.runs:
                continue
            t, y, ref = student.runs[slot]
            hot = bool(student.flags)
            ax.plot(t, y, lw=2.2 if hot else 1.2, label=student.name, **line_style(k))
            if hot:
                ends.append((student.name, t[-1], y[-1], line_style(k)["color"]))
            if ref is not None and not drawn_ref:
                # Black (no student's colour) and dotted: tab10's grey dashed is a student's.
                ax.plot(t, ref, color="black", ls=":", lw=1.0, label="_reference")
                drawn_ref = True
        _name_ends(ax, ends)
        part, what = SLOTS[slot]
        ax.set_title(f"Part ({part}): {what}", fontsize=9)
        ax.set_xlabel("time t [s]", fontsize=8)
        ax.set_ylabel("position y [m]", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(slots) :]:
        ax.set_visible(False)
    if len(students) <= MAX_LEGEND:
        handles = [axes[0].plot([], [], lw=1.5, **line_style(k))[0] for k in range(len(students))]
        fig.legend(
            handles,
            [s.name for s in students],
            loc="outside right upper",
            fontsize=8,
            handlelength=3.0,  # long enough to show a dash pattern
            ncols=1 if len(students) <= 20 else 2,
        )
    fig.suptitle(f"jaxcart class: the recordings of {len(students)} students")
    fig.savefig(path, dpi=DPI)
    return Path(path)


def _name_ends(ax, ends, gap: float = 0.075) -> None:
    """Name the runs ``ends`` [(name, t, y, colour) of each run's last sample] inside the panel,
    left of the runs' ends and in the order of their final positions, at least ``gap`` (of the
    panel's height) apart, each tied to its run's end by a thin line: runs that end together
    get names that do not."""
    if not ends:
        return
    lo, hi = ax.get_ylim()  # autoscaled to the runs drawn
    ends = sorted(ends, key=lambda e: e[2])
    at = []
    for _, _, y, _ in ends:
        f = (y - lo) / (hi - lo) if hi > lo else 0.5
        at.append(f if not at else max(f, at[-1] + gap))
    shift = max(0.0, at[-1] - 0.92)  # the top name inside the panel
    at = [max(0.04, f - shift) for f in at]
    for (name, t, y, colour), f in zip(ends, at, strict=True):
        ax.annotate(
            name,
            (t, y),
            xytext=(0.86, f),
            textcoords="axes fraction",
            ha="right",
            va="center",
            fontsize=7,
            color=colour,
            bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
            arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.6},
        )
