"""The class's page (``jaxcart class``): one self-contained HTML file (styles inline, figures
embedded as base64 PNG) with the table of every student's numbers, the spec's verdict, the
flags, the class's figures and a link to each student's report.

Rendered from a :class:`tuning.lab.classroom.ClassResult`; nothing is computed here.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

_CSS = """
body { font-family: -apple-system, 'Segoe UI', Helvetica, Arial, sans-serif; margin: 1.5em;
       line-height: 1.4; color: #222; }
h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; }
.wide { overflow-x: auto; }
table { border-collapse: collapse; margin: .6em 0; font-size: .88em; }
th, td { border: 1px solid #bbb; padding: .2em .5em; vertical-align: top; }
th { background: #f0f0f0; font-weight: normal; font-size: .9em; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.bad, span.bad { background: #fbd5d5; } td.ok { background: #dff3df; }
th:first-child, td:first-child { position: sticky; left: 0; background: #fafafa;
                                 white-space: nowrap; }
figure img { max-width: 100%; border: 1px solid #ddd; } figcaption { color: #444; }
.note { background: #fff8e0; border-left: 4px solid #e0b000; padding: .4em .8em; }
"""


def html_text(text) -> str:
    return html.escape(str(text), quote=True)


def _number(value, unit: str) -> str:
    """4 significant digits; metres as millimetres."""
    if value is None:
        return "—"
    if unit == "m":
        value = value * 1e3
    return f"{value:.4g}" if math.isfinite(value) else "does not settle within the horizon"


def _unit(unit: str) -> str:
    return "mm" if unit == "m" else unit


def page(result, figures) -> str:
    """The page as one string (figures: [(PNG path, caption)])."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>Class report: {html_text(result.folder.name)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>Class report: {html_text(result.folder)}</h1>",
        _summary(result),
        "<h2>Every student</h2>",
        _table(result),
        _flags(result),
        _constants(result),
        _figures(figures),
        "</body></html>",
    ]
    return "\n".join(p for p in parts if p) + "\n"


def _summary(result) -> str:
    c = result.counts()
    spec = result.spec
    text = (
        f"{c['students']} students (one sub-folder each): {c['complete']} complete labs, "
        f"{c['failed']} failed; run by <code>jaxcart class</code> in {result.seconds:.0f} s "
        f"with {result.workers} processes, the diagnosis section "
        f"{'on' if result.diagnosis else 'off'}. Spec (the handout's design problem), checked "
        f"on each Part (v) measured step: settling in the 2 % band under "
        f"{spec['settling_time']:g} s and overshoot under {spec['overshoot']:g} %. "
        "The same table is in <code>class.csv</code> (SI units) and <code>class.json</code>; "
        "each lab's progress is in <code>logs/</code>."
    )
    out = f"<p>{text}</p>"
    if result.stray:
        names = ", ".join(html_text(n) for n in result.stray)
        out += (
            '<p class="note">Not student folders (files at the top of the class folder, left '
            f"out): {names}.</p>"
        )
    return out


def _table(result) -> str:
    columns = result.varying()
    head = ["student", "lab", "spec", "flags"] + [
        f"{html_text(_part(c.part))}{html_text(c.label)}<br>[{html_text(_unit(c.unit))}]"
        for c in columns
    ]
    rows = ["<tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for s in result.students:
        name = html_text(s.name)
        cells = [f'<a href="{html_text(s.report)}">{name}</a>' if s.report else name]
        lab = "complete" if s.complete else f"failed: {html_text(s.error)}"
        row = [f"<td>{cells[0]}</td>", f'<td class="{"ok" if s.complete else "bad"}">{lab}</td>']
        v = s.verdict
        row.append(f'<td class="{ {"pass": "ok", "fail": "bad"}.get(v, "") }">{v}</td>')
        row.append(f'<td class="{"bad" if s.flags else ""}">{len(s.flags) or ""}</td>')
        for c in columns:
            hot = " bad" if c.key in s.marked else ""
            row.append(f'<td class="num{hot}">{_number(s.value(c.key), c.unit)}</td>')
        rows.append("<tr>" + "".join(row) + "</tr>")
    return '<div class="wide"><table>' + "\n".join(rows) + "</table></div>"


def _part(part: str) -> str:
    return "" if not part or part == "pre-lab" else f"({part}) "


def _flags(result) -> str:
    flagged = [s for s in result.students if s.flags]
    if not flagged:
        return (
            "<h2>Flags</h2><p>Nothing flagged: every lab complete, every part recorded, every "
            "file used, no cart parameter ten times off the class's median.</p>"
        )
    items = []
    for s in sorted(flagged, key=lambda s: (s.complete, s.name)):
        inner = "".join(f"<li>{html_text(f)}</li>" for f in s.flags)
        items.append(f"<li><b>{html_text(s.name)}</b><ul>{inner}</ul></li>")
    return (
        "<h2>Flags</h2><p>Failed labs, parts lost to a file that cannot be used, missing "
        "parts, files the lab did not use, and estimates of cart parameters (kg/s, N) ten "
        "times off the class's median or more:</p>"
        f"<ul>{''.join(items)}</ul>"
    )


def _constants(result) -> str:
    if not result.constant:
        return ""
    rows = ["<tr><th>number</th><th>value</th><th>unit</th></tr>"]
    for c in result.columns:
        if c.key in result.constant:
            rows.append(
                f"<tr><td>{html_text(_part(c.part) + c.label)}</td>"
                f'<td class="num">{_number(result.constant[c.key], c.unit)}</td>'
                f"<td>{html_text(_unit(c.unit))}</td></tr>"
            )
    return (
        "<h2>The same for every student</h2><p>Numbers of the pre-lab on the handout's model, "
        "equal in every complete lab (not repeated in the table):</p>"
        f"<table>{''.join(rows)}</table>"
    )


def _figures(figures) -> str:
    out = ["<h2>The class's figures</h2>"] if figures else []
    for path, caption in figures:
        data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
        out.append(
            f'<figure><img alt="{html_text(Path(path).name)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html_text(caption)}</figcaption></figure>"
        )
    return "\n".join(out)
