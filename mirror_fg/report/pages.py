"""The report's two renderings of one list of blocks: a self-contained HTML page and an A4 PDF.

The report (:mod:`mirror_fg.report.writer`) says what it has to say once, as :class:`Block` s (headings,
paragraphs, tables, lists, preformatted text, figures); :func:`html_page` and :func:`pdf_document` render
the same blocks, so the PDF holds everything the HTML does (flagged measurements, ROS snippets, frames,
the input echo), every PDF page A4 portrait. A figure is rendered once (:class:`RenderedFigure`) for both.
"""
from __future__ import annotations

import base64
import html
import io
import textwrap
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from mirror_fg.report.figures import new_figure, png

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["Block", "RenderedFigure", "html_page", "pdf_document", "A4_INCHES"]

A4_INCHES = (8.27, 11.69)
#: Resolution of a figure placed on a PDF page (dots per inch).
PDF_FIGURE_DPI = 150
_CSS = """
body { font-family: 'DejaVu Sans', Arial, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table.summary { border-collapse: collapse; font-size: 0.9em; }
table.summary td { border: 1px solid #ddd; padding: 3px 8px; vertical-align: top; }
table.summary td.v { font-family: 'DejaVu Sans Mono', monospace; }
.verdict { padding: 0.6em 1em; border-radius: 4px; margin: 0.8em 0; }
.good { background: #e6f4e6; border: 1px solid #8c8; } .bad { background: #fbe9e7; border: 1px solid #d88; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #555; }
pre { background: #f6f6f6; padding: 0.6em; font-size: 0.8em; white-space: pre-wrap; overflow-wrap: anywhere; }
.note { font-style: italic; color: #666; } .flagged { color: #b00; }
"""


@dataclass
class Block:
    """One piece of the report. ``kind``: ``h2``, ``p``, ``note``, ``pre``, ``table`` (``rows``: label,
    value; a value's lines split on newlines), ``list`` (``items``), ``verdict`` (``good``), ``figure``
    (``figure``, ``text`` its caption). ``id``: an HTML id (lists, for tests and links)."""

    kind: str
    text: str = ""  # a verdict's headline (its reasons in ``items``)
    rows: list[tuple[str, str]] = field(default_factory=list)
    items: list[str] = field(default_factory=list)
    figure: Any = None
    good: bool = True
    id: str = ""
    css: str = ""


def html_page(title: str, blocks: list[Block]) -> str:
    """The self-contained HTML page (CSS inline, figures as base64 PNG, no scripts or external resources)."""
    e = html.escape
    parts = ["<!DOCTYPE html>", "<html lang='en'><head><meta charset='utf-8'>",
             f"<title>{e(title)}</title><style>{_CSS}</style></head><body>", f"<h1>{e(title)}</h1>"]
    for b in blocks:
        ident = f" id='{e(b.id)}'" if b.id else ""
        if b.kind == "h2":
            parts.append(f"<h2{ident}>{e(b.text)}</h2>")
        elif b.kind in ("p", "note"):
            parts.append(f"<p{ident} class='{'note' if b.kind == 'note' else b.css}'>{e(b.text)}</p>")
        elif b.kind == "verdict":
            reasons = "".join(f"<li>{e(x)}</li>" for x in b.items)
            parts.append(f"<div class='verdict {'good' if b.good else 'bad'}'><strong>{e(b.text)}</strong>"
                         + (f"<ul>{reasons}</ul>" if reasons else "") + "</div>")
        elif b.kind == "pre":
            parts.append(f"<pre{ident}>{e(b.text)}</pre>")
        elif b.kind == "table":
            rows = "".join(f"<tr><td>{e(k)}</td><td class='v'>{'<br>'.join(e(x) for x in v.split(chr(10)))}</td></tr>"
                           for k, v in b.rows)
            parts.append(f"<table class='summary'{ident}>{rows}</table>")
        elif b.kind == "list":
            items = "".join(f"<li class='{b.css}'>{e(x)}</li>" if b.css else f"<li>{e(x)}</li>" for x in b.items)
            parts.append(f"<ul{ident}>{items}</ul>")
        elif b.kind == "figure":
            data = base64.b64encode(figure_png(b.figure)).decode("ascii")
            parts.append(f"<figure><img alt='{e(b.text[:80])}' src='data:image/png;base64,{data}'>"
                         f"<figcaption>{e(b.text)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


class RenderedFigure:
    """A figure rendered once, as PNG at PDF_FIGURE_DPI: the HTML and the PDF embed the same bytes."""

    def __init__(self, figure: Figure) -> None:
        self.png = png(figure, PDF_FIGURE_DPI)


def figure_png(figure: Figure | RenderedFigure) -> bytes:
    """The PNG of a figure, rendered now unless it already was (:class:`RenderedFigure`)."""
    return figure.png if isinstance(figure, RenderedFigure) else png(figure, PDF_FIGURE_DPI)


class _Pages:
    """A4 text pages filled top to bottom; a new page when the next line does not fit."""

    TOP, BOTTOM, LEFT, LINE = 0.955, 0.045, 0.06, 0.0135

    def __init__(self, pdf: Any, title: str) -> None:
        self.pdf, self.title, self.y = pdf, title, 0.0
        self.fig: Figure | None = None

    def _page(self) -> Figure:
        """Close the current page and start a new one (the new ``self.fig``)."""
        self.close()
        fig = self.fig = new_figure(*A4_INCHES)
        fig.set_layout_engine("none")
        fig.text(self.LEFT, 0.985, self.title, fontsize=7, color="#888", va="top")
        self.y = self.TOP
        return fig

    def close(self) -> None:
        if self.fig is not None:
            self.pdf.savefig(self.fig)
            self.fig = None

    def line(self, text: str, *, size: float = 8.0, x: float = 0.0, space: float = 1.0, **style: Any) -> None:
        fig = self.fig
        if fig is None or self.y - self.LINE * space < self.BOTTOM:
            fig = self._page()
        fig.text(self.LEFT + x, self.y, text, fontsize=size, va="top", **style)
        self.y -= self.LINE * space * size / 8.0

    def ensure(self, lines: int) -> None:
        """A new page unless ``lines`` more lines fit on this one."""
        if self.fig is None or self.y - self.LINE * lines < self.BOTTOM:
            self._page()

    def gap(self, lines: float = 0.6) -> None:
        self.y -= self.LINE * lines

    #: A figure takes at most this fraction of the page's height, so that two or three share a page.
    FIGURE_HEIGHT = 0.40

    def figure(self, heading: str, figure: Figure | RenderedFigure, caption: str) -> None:
        """A figure scaled to the page width (aspect kept, at most FIGURE_HEIGHT of the page), heading
        above, caption below; on this page when it fits, else at the top of the next."""
        import matplotlib.image

        image = matplotlib.image.imread(io.BytesIO(figure_png(figure)), format="png")
        captions = _wrap(caption, 110)
        h, w = image.shape[:2]
        width = 1.0 - 2 * self.LEFT
        height = min(width * (h / w) * A4_INCHES[0] / A4_INCHES[1], self.FIGURE_HEIGHT)
        width = height * (w / h) * A4_INCHES[1] / A4_INCHES[0]
        needed = self.LINE * (2.0 + 1.8 * 12 / 8) + height + 0.015 + self.LINE * len(captions)
        if self.fig is None or self.y - needed < self.BOTTOM:
            self._page()
        else:
            self.gap(1.5)
        self.line(heading, size=12, weight="bold", space=1.8)
        assert self.fig is not None
        ax = self.fig.add_axes((self.LEFT, self.y - height, width, height))
        ax.imshow(image, interpolation="none")  # embedded as it is: no resampling in the PDF backend
        ax.set_axis_off()
        self.y -= height + 0.015
        for line in captions:
            self.line(line, size=8, style="italic")


def _wrap(text: str, width: int) -> list[str]:
    return [w for line in text.split("\n") for w in (textwrap.wrap(line, width) or [""])]


def pdf_document(title: str, blocks: list[Block]) -> bytes:
    """The same blocks as an A4 PDF: text flowed over pages, the figures after it, several to a page."""
    from matplotlib.backends.backend_pdf import PdfPages

    buf = io.BytesIO()
    with PdfPages(buf, metadata={"Title": title, "Creator": "mirror-fg"}) as pdf:
        pages = _Pages(pdf, title)
        pages.line(title, size=15, weight="bold", space=2.2)
        heading = ""
        for k, b in enumerate(blocks):
            if b.kind == "h2":
                heading = b.text
                if k + 1 < len(blocks) and blocks[k + 1].kind == "figure":
                    continue  # the figure carries its heading
                pages.ensure(6)  # no heading alone at the foot of a page
                pages.gap()
                pages.line(b.text, size=11, weight="bold", space=1.6)
            elif b.kind in ("p", "note", "verdict"):
                colour = {"verdict": "darkgreen" if b.good else "darkred"}.get(b.kind, "#222")
                for line in _wrap(b.text, 100 if b.kind == "verdict" else 118):
                    pages.line(line, color=colour, style="italic" if b.kind == "note" else "normal",
                               **({"size": 11.0, "weight": "bold", "space": 1.5} if b.kind == "verdict" else {}))  # type: ignore[arg-type]
                for item in b.items:  # a verdict's reasons
                    for k, line in enumerate(_wrap(item, 112)):
                        pages.line(("• " if k == 0 else "  ") + line, color=colour)
                pages.gap(0.4)
            elif b.kind == "pre":
                for line in b.text.split("\n"):
                    for part in textwrap.wrap(line, 112, subsequent_indent="    ") or [""]:
                        pages.line(part, size=7, family="monospace")
                pages.gap(0.4)
            elif b.kind == "table":
                for label, value in b.rows:
                    label_lines = textwrap.wrap(label, 52) or [""]
                    value_lines = [p for v in value.split("\n") for p in (textwrap.wrap(v, 62) or [""])]
                    pages.ensure(max(len(label_lines), len(value_lines)))
                    for k in range(max(len(label_lines), len(value_lines))):
                        if k < len(label_lines):
                            pages.line(label_lines[k], size=7.5, weight="bold", space=0.0)
                        pages.line(value_lines[k] if k < len(value_lines) else "", size=7.5, x=0.46,
                                   family="monospace")
                    pages.gap(0.25)
            elif b.kind == "list":
                for item in b.items:
                    for k, line in enumerate(_wrap(item, 112)):
                        pages.line(("• " if k == 0 else "  ") + line, color="#b00" if b.css == "flagged" else "#222")
            elif b.kind == "figure":
                pages.figure(heading, b.figure, b.text)
        pages.close()
    return buf.getvalue()
