"""The one check of a figure the tool writes, at the size it is written: every artist inside the
canvas (a legend cut off at an edge is the usual failure) and no legend entry twice, nor one
that only repeats another with a qualifier ("corrected" beside "corrected (coulomb)").

``tests/conftest.py`` runs it on every figure any test saves (``Figure.savefig``), so a figure
is checked wherever it is written; ``tests/test_figures.py`` writes each kind at least once.
"""

from __future__ import annotations

import re

#: Pixels an artist may reach past the canvas (antialiasing, rounding).
SLACK_PX = 1.0


def figure_problems(fig) -> list[str]:
    """What is wrong with ``fig`` as drawn at its size and dpi: one line per clipped artist
    (its kind, its text and by how many pixels), per repeated legend entry."""
    from matplotlib.backend_bases import _get_renderer

    renderer = _get_renderer(fig)
    canvas = fig.bbox
    out = []
    for name, artist in _artists(fig):
        try:
            box = artist.get_tightbbox(renderer) if hasattr(artist, "get_tightbbox") else None
        except (RuntimeError, ValueError):  # an artist that cannot say where it is
            continue
        if box is None or not (box.width > 0 or box.height > 0):
            continue
        over = {
            "left": canvas.x0 - box.x0,
            "right": box.x1 - canvas.x1,
            "bottom": canvas.y0 - box.y0,
            "top": box.y1 - canvas.y1,
        }
        cut = {side: px for side, px in over.items() if px > SLACK_PX}
        if cut:
            where = ", ".join(f"{px:.0f} px past the {side} edge" for side, px in cut.items())
            out.append(
                f"{name} is cut off: {where} of the {canvas.width:.0f}x"
                f"{canvas.height:.0f} px canvas"
            )
    for name, legend in _legends(fig):
        out += [
            f"{name}: {p}" for p in repeated_entries([t.get_text() for t in legend.get_texts()])
        ]
    return out


def repeated_entries(labels) -> list[str]:
    """Legend labels given twice, or given once more with a qualifier added."""
    out = []
    norm = [re.sub(r"\s+", " ", label.strip().lower()) for label in labels]
    for i, a in enumerate(norm):
        for j in range(i + 1, len(norm)):
            b = norm[j]
            if a == b:
                out.append(f"entry {labels[i]!r} twice")
            elif _qualified(a, b) or _qualified(b, a):
                out.append(f"entries {labels[i]!r} and {labels[j]!r} say the same")
    return out


def _qualified(short: str, long: str) -> bool:
    return long.startswith(short) and long[len(short) :].lstrip()[:1] in ("(", ",", ":", "-")


def _legends(fig):
    for k, legend in enumerate(fig.legends):
        yield f"figure legend {k + 1}", legend
    for ax in _all_axes(fig):
        legend = ax.get_legend()
        if legend is not None:
            yield f"legend of axes {_label(ax)!r}", legend


def _artists(fig):
    """(name, artist) of what a reader must see: each axes with all it draws (ticks, labels,
    title, its own legend), each figure legend, the figure's own texts."""
    for ax in _all_axes(fig):
        if ax.get_visible():
            yield f"axes {_label(ax)!r} (with its labels and ticks)", ax
    yield from _legends(fig)
    for text in fig.texts:
        if text.get_visible() and text.get_text():
            yield f"figure text {text.get_text()[:40]!r}", text
    for attr in ("_suptitle", "_supxlabel", "_supylabel"):
        text = getattr(fig, attr, None)
        if text is not None and text.get_visible() and text.get_text():
            yield f"figure title {text.get_text()[:40]!r}", text


def _all_axes(fig):
    seen = []
    stack = list(fig.axes)
    while stack:
        ax = stack.pop(0)
        if ax in seen:
            continue
        seen.append(ax)
        stack += [c for c in ax.child_axes if c not in seen]
    return seen


def _label(ax) -> str:
    return ax.get_title() or ax.get_ylabel() or ax.get_label() or "untitled"
