"""The pieces the HTML report is built of: escaped text, tables, notes, sections, figures.

Cells and inner parts are HTML already: escape text with :func:`escape` before.
"""

from __future__ import annotations

import html
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from lidarcal_ros.io.report import figures

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "FigureRenderer", "Progress", "escape", "facts_table", "html_section", "html_table",
    "note",
]

#: ``progress(stage, fraction)`` as the report's stages call it.
Progress = Callable[[str, float], None]


def escape(text: object) -> str:
    """``text`` as HTML text (``&``, ``<``, ``>`` and quotes escaped)."""
    return html.escape(str(text))


def html_table(header: Sequence[str], rows: Sequence[Sequence[str]], numeric: set[int],
               *, row_classes: Sequence[str] | None = None) -> str:
    """An HTML table (no header row for an empty ``header``); cells are HTML already
    (escape before); columns in ``numeric`` right aligned."""
    head = "<thead><tr>" + "".join(f"<th>{h}</th>" for h in header) + "</tr></thead>" \
        if header else ""
    body = "".join(
        (f'<tr class="{row_classes[r]}">' if row_classes and row_classes[r] else "<tr>")
        + "".join(f'<td class="num">{c}</td>' if i in numeric else f"<td>{c}</td>"
                  for i, c in enumerate(row)) + "</tr>"
        for r, row in enumerate(rows))
    return f"<table>{head}<tbody>{body}</tbody></table>"


def facts_table(pairs: Sequence[tuple[str, str]]) -> str:
    """A table of (label, value) lines, without a header; both escaped here."""
    return html_table([], [[escape(k), escape(v)] for k, v in pairs], set())


def note(text: str) -> str:
    """A note paragraph (small, grey) of ``text`` (HTML)."""
    return f'<p class="note">{text}</p>'


class FigureRenderer:
    """Draws the figures one by one, saying how far it is."""

    def __init__(self, n_figures: int, progress: Progress | None) -> None:
        self.n_figures = max(n_figures, 1)
        self.done = 0
        self.progress = progress

    def figure(self, fig_id: str, alt: str, fig: Figure, caption: str = "") -> str:
        """A ``<figure>`` holding ``fig`` as an embedded PNG."""
        if self.progress is not None:
            self.progress("drawing figures", self.done / self.n_figures)
        img = (f'<img id="{html.escape(fig_id)}" class="figure" alt="{html.escape(alt)}" '
               f'src="data:image/png;base64,{figures.png_base64(fig)}">')
        self.done += 1
        cap = f"<figcaption>{caption}</figcaption>" if caption else ""
        return f"<figure>{img}{cap}</figure>"


def html_section(key: str, title: str, inner: Sequence[str]) -> str:
    """``<section id="key">`` with the heading ``title`` (escaped here) over ``inner``."""
    return f'<section id="{key}">\n<h2>{escape(title)}</h2>\n' + "\n".join(inner) + \
        "\n</section>"

