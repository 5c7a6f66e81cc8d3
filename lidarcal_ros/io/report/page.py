"""The calibration report as one self-contained HTML file (``lidarcal report``).

Its sections, their ids and the rendering check: docs/internals.md, "The HTML report".
"""


from __future__ import annotations

import logging
from pathlib import Path

from lidarcal_ros.errors import OutputError
from lidarcal_ros.io.output_files import EXISTS, write_text
from lidarcal_ros.io.report.content import ReportContent
from lidarcal_ros.io.report.elements import FigureRenderer, Progress, escape
from lidarcal_ros.io.report.sections import (
    block_html,
    calibration_html,
    control_html,
    evaluation_html,
    pairs_html,
    provenance_html,
    quality_html,
    radiometry_html,
    summary_html,
    swath_html,
    trajectory_html,
)

__all__ = ["figure_ids", "render_html", "write_html_report"]

logger = logging.getLogger(__name__)

_STYLE = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1250px; color: #222;
       line-height: 1.4; padding: 0 1em; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.8em;
     border-bottom: 1px solid #ccc; } h3 { font-size: 1.0em; margin-bottom: 0.2em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; vertical-align: top; }
th { background: #f2f2f2; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.mono { font-family: monospace; font-size: 0.9em; word-break: break-all; }
figure { margin: 0.8em 0; } figure img { max-width: 100%; height: auto; }
figcaption { font-size: 0.9em; color: #555; }
.OK, .met { color: #1a7f37; font-weight: bold; } .WARN { color: #9a6700; font-weight: bold; }
.ERROR, .missed { color: #cf222e; font-weight: bold; } .note { color: #555; font-size: 0.9em; }
.statement { font-size: 1.1em; padding: 0.5em 0.8em; background: #f6f8fa;
             border-left: 4px solid #888; }
nav a { margin-right: 0.8em; } details summary { cursor: pointer; }
tr.changed td { background: #fff8c5; }
"""

_SCRIPT = """
window.addEventListener("load", function () {
  var images = document.images, rendered = 0;
  for (var i = 0; i < images.length; i++) {
    var ok = images[i].complete && images[i].naturalWidth > 0;
    images[i].setAttribute("data-rendered", ok ? "1" : "0");
    if (ok) { rendered++; }
  }
  document.body.setAttribute("data-figures-total", String(images.length));
  document.body.setAttribute("data-figures-rendered", String(rendered));
});
"""

_SECTIONS = (("summary", "Summary"), ("quality", "Quality level"), ("block", "Block"),
             ("calibration", "Calibration"), ("trajectory", "Trajectory errors"),
             ("swath", "Swath differences"),
             ("pairs", "Strip pairs"), ("evaluation", "Accuracy"),
             ("control", "Control points"), ("radiometry", "Radiometry"),
             ("provenance", "Provenance"))


def figure_ids(content: ReportContent) -> set[str]:
    """The ``id`` of every figure the report of ``content`` holds."""
    ids = {f"fig-pair-{a}-{b}" for a, b in (p.strips for p in content.pairs)}
    if len(content.correlation_names) >= 2:
        ids.add("fig-correlation")
    if content.flight is not None:
        ids.add("fig-flight-map")
    if content.swath is not None and content.swath.pairs:
        ids.add("fig-swath-dz")
    if content.radiometry is not None:
        ids |= {"fig-vmr-slope", "fig-reflectance-map"}
    if content.trajectory is not None:
        ids.add("fig-trajectory-errors")
    return ids


def render_html(content: ReportContent, *, progress: Progress | None = None) -> str:
    """The report as one HTML document (docs/internals.md, "The HTML report")."""
    draw = FigureRenderer(len(figure_ids(content)), progress)
    nav = "".join(f'<a href="#{key}">{escape(name)}</a>' for key, name in _SECTIONS
                  if key != "trajectory" or content.trajectory is not None)
    parts = [f"<h1>{escape(content.title)}</h1>", f"<nav>{nav}</nav>",
             summary_html(content), quality_html(content), block_html(content, draw),
             calibration_html(content, draw), trajectory_html(content, draw),
             swath_html(content, draw),
             pairs_html(content, draw), evaluation_html(content.evaluation),
             control_html(content.control), radiometry_html(content, draw),
             provenance_html(content.provenance)]
    body = "\n".join(parts)
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{escape(content.title)}</title>\n<style>{_STYLE}</style>\n"
            f"<script>{_SCRIPT}</script>\n</head>\n<body>\n{body}\n</body>\n</html>\n")


def write_html_report(path: str | Path, content: ReportContent, *, overwrite: bool = False,
                      progress: Progress | None = None) -> Path:
    """Render ``content`` and write it to ``path`` (atomically: a reader never sees half a
    file).

    Raises
    ------
    OutputError
        ``path`` exists and ``overwrite`` is False, or it cannot be written (nothing partial
        is left, a previous report is untouched).
    """
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise OutputError(f"{path}: {EXISTS}")
    text = render_html(content, progress=progress)
    write_text(path, text, what="the report", overwrite=overwrite)
    logger.info("report written to %s (%d bytes)", path, len(text))
    return path
