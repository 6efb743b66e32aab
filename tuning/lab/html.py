"""The report as a list of blocks, rendered twice: Markdown (report.md, figures linked) and
self-contained HTML (report.html, figures embedded as base64 PNG or SVG; a PDF figure by its
PNG copy).

Building blocks rather than parsing Markdown keeps both renderings exact. Inline text may use
`code` and **bold**; everything else is escaped in the HTML.

>>> doc = Document("Lab")
>>> doc.paragraph("gamma = `1.7235` N/V")
>>> "<code>1.7235</code>" in doc.to_html(".")
True
"""

from __future__ import annotations

import base64
import html
import re
from dataclasses import dataclass, field
from pathlib import Path

_CSS = """
body { font-family: -apple-system, 'Segoe UI', Helvetica, Arial, sans-serif; max-width: 60em;
       margin: 2em auto; padding: 0 1em; line-height: 1.45; color: #222; }
h1, h2, h3 { line-height: 1.2; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; }
table { border-collapse: collapse; margin: .8em 0; }
th, td { border: 1px solid #bbb; padding: .25em .6em; text-align: left; }
th { background: #f0f0f0; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
code { background: #f4f4f4; padding: 0 .2em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: .92em; color: #444; }
.note { background: #fff8e0; border-left: 4px solid #e0b000; padding: .4em .8em; }
"""


@dataclass
class Document:
    """A report: a title and blocks (heading, paragraph, note, bullets, table, figure)."""

    title: str
    blocks: list = field(default_factory=list)

    def heading(self, text: str, level: int = 2) -> None:
        self.blocks.append(("heading", level, text))

    def paragraph(self, text: str) -> None:
        self.blocks.append(("paragraph", text))

    def note(self, text: str) -> None:
        """A highlighted paragraph (synthetic data, missing recordings)."""
        self.blocks.append(("note", text))

    def bullets(self, items) -> None:
        self.blocks.append(("bullets", [str(i) for i in items]))

    def table(self, header, rows, numeric=None) -> None:
        """A table; ``numeric`` (a list of booleans per column) right-aligns numbers in HTML."""
        rows = [[str(c) for c in row] for row in rows]
        numeric = list(numeric) if numeric is not None else [False] * len(header)
        self.blocks.append(("table", [str(h) for h in header], rows, numeric))

    def figure(self, path: str, caption: str) -> None:
        """A figure: ``path`` relative to the report's folder (e.g. figures/tap.png)."""
        self.blocks.append(("figure", path, caption))

    # ------------------------------------------------------------------ Markdown

    def to_markdown(self) -> str:
        out = [f"# {self.title}", ""]
        for block in self.blocks:
            kind = block[0]
            if kind == "heading":
                out += ["#" * block[1] + " " + block[2], ""]
            elif kind == "paragraph":
                out += [block[1], ""]
            elif kind == "note":
                out += ["> " + block[1], ""]
            elif kind == "bullets":
                out += [f"- {item}" for item in block[1]] + [""]
            elif kind == "table":
                _, header, rows, numeric = block
                out.append("| " + " | ".join(header) + " |")
                out.append("|" + "|".join("---:" if n else "---" for n in numeric) + "|")
                out += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows]
                out.append("")
            elif kind == "figure":
                _, path, caption = block
                out += [f"![{caption}]({path})", "", f"*{caption}*", ""]
        return "\n".join(out).rstrip() + "\n"

    # ------------------------------------------------------------------ HTML

    def to_html(self, root) -> str:
        """The report as one HTML page; figures read from ``root`` / path and embedded."""
        root = Path(root)
        body = [f"<h1>{_inline(self.title)}</h1>"]
        for block in self.blocks:
            kind = block[0]
            if kind == "heading":
                level = block[1]
                anchor = re.sub(r"[^a-z0-9]+", "-", block[2].lower()).strip("-")
                body.append(f'<h{level} id="{anchor}">{_inline(block[2])}</h{level}>')
            elif kind == "paragraph":
                body.append(f"<p>{_inline(block[1])}</p>")
            elif kind == "note":
                body.append(f'<p class="note">{_inline(block[1])}</p>')
            elif kind == "bullets":
                items = "".join(f"<li>{_inline(i)}</li>" for i in block[1])
                body.append(f"<ul>{items}</ul>")
            elif kind == "table":
                _, header, rows, numeric = block
                head = "".join(f"<th>{_inline(h)}</th>" for h in header)
                lines = []
                for row in rows:
                    cells = "".join(
                        f'<td class="num">{_inline(c)}</td>' if n else f"<td>{_inline(c)}</td>"
                        for c, n in zip(row, numeric, strict=False)
                    )
                    lines.append(f"<tr>{cells}</tr>")
                body.append(f"<table><tr>{head}</tr>{''.join(lines)}</table>")
            elif kind == "figure":
                _, path, caption = block
                mime, data = _embedded(root / path)
                body.append(
                    f'<figure><img alt="{html.escape(caption)}" '
                    f'src="data:{mime};base64,{data}">'
                    f"<figcaption>{_inline(caption)}</figcaption></figure>"
                )
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head>\n<body>\n"
            + "\n".join(body)
            + "\n</body></html>\n"
        )


#: What an <img> can show, by suffix; a PDF figure is shown by its PNG copy beside it.
_MIME = {".png": "image/png", ".svg": "image/svg+xml"}


def _embedded(path: Path) -> tuple[str, str]:
    """(MIME type, base64 data) of a figure for the page: PNG and SVG as they are, a PDF by
    the PNG of the same name."""
    if path.suffix.lower() not in _MIME:
        path = path.with_suffix(".png")
    return _MIME[path.suffix.lower()], base64.b64encode(path.read_bytes()).decode("ascii")


def _inline(text: str) -> str:
    """Escape, then render `code`, **bold** and links to sections, [text](#anchor)."""
    parts = re.split(r"(`[^`]*`)", text)
    out = []
    for part in parts:
        if len(part) >= 2 and part.startswith("`") and part.endswith("`"):
            out.append(f"<code>{html.escape(part[1:-1])}</code>")
        else:
            escaped = html.escape(part)
            escaped = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", escaped)
            out.append(re.sub(r"\[([^\]]+)\]\((#[a-z0-9-]+)\)", r'<a href="\2">\1</a>', escaped))
    return "".join(out)
