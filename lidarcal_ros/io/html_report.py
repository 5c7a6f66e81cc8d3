"""The calibration report as one self-contained HTML file (``lidarcal report``).

What the report holds is described by :class:`ReportContent` (filled by
:mod:`lidarcal_ros.pipeline.report`); the figures come from
:mod:`lidarcal_ros.io.report_figures`. The file has every figure as a base64 PNG ``<img>``
with an ``id`` and an ``alt`` text, and the style sheet and a small script inline: nothing
is fetched, so it reads offline and can be mailed as it is.

Sections, in the order a LiDAR processor reads them:

- a summary: mission, the USGS LBS quality level met, the calibration;
- quality level: each LBS measure against the thresholds of QL0-QL3;
- the block: flight lines, trajectory, control and check points on a map (map coordinates,
  CRS named), and a table per strip (time, points, length, heading, speed, height above
  ground, density);
- the calibration: its facts, the bias table (estimate, sigma, unit, or why a parameter was
  not estimated), the correlation matrix;
- swath-to-swath height differences over the block before and after (mosaics on one colour
  scale, per pair RMSDz and largest |dz|), then per strip pair the normal discrepancies of the
  calibration's sample points (maps on one scale, histograms);
- relative and absolute accuracy as ``lidarcal evaluate`` measures them: the rigid
  transformation co-aligning each pair (point-to-patch ICP) and the check-point residuals;
- the control-point residuals;
- the radiometric correction: what the reflectance is, the variance-to-mean ratio against
  terrain slope before and after (the paper's Fig. 5), maps of intensity and reflectance;
- provenance: lidarcal version, date, command, every input with its size and SHA-256, the
  flight configuration.

The inline script marks every ``<img>`` that decoded (``data-rendered="1"``) and writes
``data-figures-total`` and ``data-figures-rendered`` on ``<body>`` once the page has loaded,
so a headless browser can tell that every figure rendered. Every section is a ``<section>``
with an ``id`` (``summary``, ``quality``, ``block``, ``calibration``, ``swath``,
``pairs``, ``evaluation``, ``control``, ``radiometry``, ``provenance``).
"""

from __future__ import annotations

import html
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lidarcal_ros.core.calibration_result import ControlResidual, PairDiscrepancies
from lidarcal_ros.core.evaluation import RIGID_NAMES, AccuracySummary, RigidFit
from lidarcal_ros.core.params import display_value
from lidarcal_ros.core.quality_level import LBS_LEVELS, QualityAssessment
from lidarcal_ros.core.swath_differences import DzStatistics, SwathDifferences
from lidarcal_ros.core.units import format_cm, format_number
from lidarcal_ros.errors import OutputError
from lidarcal_ros.io import report_figures as figures
from lidarcal_ros.io.output_files import EXISTS, write_text

if TYPE_CHECKING:
    from matplotlib.figure import Figure

logger = logging.getLogger(__name__)

Progress = Callable[[str, float], None]


# ---------------------------------------------------------------------------- content
@dataclass
class BiasEntry:
    """One row of the bias table.

    Attributes
    ----------
    name : str
        Parameter key (method.md section 1).
    value : float
        Estimate or fixed value, SI units (m, rad, 1).
    sigma : float or None
        Standard deviation, SI units; None where not estimated.
    state : str
        ``estimated``, ``fixed`` (held at ``value``, not solved for) or ``not_estimable``.
    reason : str
        Why a parameter was not estimable (words from the observability analysis).
    """

    name: str
    value: float
    sigma: float | None
    state: str
    reason: str = ""


@dataclass
class PairSection:
    """Normal discrepancies of one strip pair before and after calibration.

    Attributes
    ----------
    before, after : PairDiscrepancies
        At zero biases and at the estimate (the same sample points; metres).
    qa_level : str
        ``OK``, ``WARN`` or ``ERROR`` for the RMS after (thresholds of the configuration).
    coverage : float or None
        Fraction of the smaller strip's footprint the pair overlaps (from the calibration
        file), if known.
    """

    before: PairDiscrepancies
    after: PairDiscrepancies
    qa_level: str
    coverage: float | None = None

    @property
    def strips(self) -> tuple[int, int]:
        return self.after.strips


@dataclass
class SlopeClass:
    """Intensity statistics of the points whose terrain slope falls in ``[lo_deg, hi_deg)``.

    Attributes
    ----------
    lo_deg, hi_deg : float
        Slope bounds, degrees from horizontal.
    n_points : int
        Points used (corrected, with a normal and an intensity, not rough).
    vmr_intensity, vmr_reflectance : float
        Variance-to-mean ratio of the recorded intensity and of the reflectance put on the
        intensity's scale (one factor for all classes: equal means over every point used),
        intensity units; NaN for too few points.
    mean_intensity, mean_reflectance : float
        Means, intensity units and the reflectance's unit.
    """

    lo_deg: float
    hi_deg: float
    n_points: int
    vmr_intensity: float
    vmr_reflectance: float
    mean_intensity: float
    mean_reflectance: float

    @property
    def change(self) -> float:
        """Relative change of the VMR, ``after / before - 1`` (NaN when undefined)."""
        if not (math.isfinite(self.vmr_intensity) and self.vmr_intensity > 0
                and math.isfinite(self.vmr_reflectance)):
            return math.nan
        return self.vmr_reflectance / self.vmr_intensity - 1.0


@dataclass
class MapRaster:
    """A grid of values over the mission, rows from south to north.

    Attributes
    ----------
    values : (ny, nx) float64
        Per cell, NaN where no point fell.
    x0, y0 : float
        Map-frame coordinates of the south-west corner of cell ``[0, 0]``, metres.
    cell_m : float
        Cell size, metres.
    """

    values: np.ndarray
    x0: float
    y0: float
    cell_m: float

    def extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)``, map frame, metres (for ``imshow``)."""
        ny, nx = self.values.shape
        return self.x0, self.x0 + nx * self.cell_m, self.y0, self.y0 + ny * self.cell_m


@dataclass
class RadiometrySection:
    """The radiometric part of the report.

    Attributes
    ----------
    slope_classes : list of SlopeClass
    intensity, reflectance : MapRaster
        Mean recorded intensity and mean reflectance per cell, on one grid.
    n_points, n_used : int
        Points corrected, and points entering the slope statistics.
    meaning : str
        What the reflectance is (:attr:`~lidarcal_ros.core.radiometry.RadiometricModel.meaning`).
    unit : str
        Its unit: ``1`` (Lambertian reflectance) or ``intensity units`` (relative).
    notes : list of str
        Sentences shown under the figures (atmosphere, reference target, points left out).
    """

    slope_classes: list[SlopeClass]
    intensity: MapRaster
    reflectance: MapRaster
    n_points: int
    n_used: int
    meaning: str = ""
    unit: str = "intensity units"
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class InputFile:
    """One input of the report: role, path, size (bytes) and SHA-256 (hex) of its content
    (of a directory: of its files' names and contents, in name order)."""

    role: str
    path: str
    size_bytes: int
    sha256: str


@dataclass
class Provenance:
    """What produced the report.

    Attributes
    ----------
    version : str
        lidarcal's.
    generated : str
        When, ISO 8601 UTC.
    command : str
        The command line, when run from one.
    inputs : list of InputFile
    configuration : list of (str, str, bool)
        Every flight-configuration parameter: name, value, whether it differs from the
        default.
    configuration_source : str
        The parameters file, or ``defaults``.
    """

    version: str
    generated: str
    command: str
    inputs: list[InputFile]
    configuration: list[tuple[str, str, bool]]
    configuration_source: str


@dataclass(frozen=True)
class StripRow:
    """One flight line (strip) of the block.

    Attributes
    ----------
    strip_id : int
    points : int
    start : str
        First point's time: ISO 8601 UTC for absolute times, else seconds.
    duration_s, length_m : float
        Time from first to last point and the trajectory's length over it.
    heading_deg : float
        Course over ground, degrees clockwise from grid north (0-360).
    speed_mps : float
    height_m : float
        Flying height above the ground: median trajectory height minus median point height.
    density_per_m2 : float
        Points over the footprint's area (cells holding points).
    """

    strip_id: int
    points: int
    start: str
    duration_s: float
    length_m: float
    heading_deg: float
    speed_mps: float
    height_m: float
    density_per_m2: float


@dataclass
class FlightMap:
    """What the block map shows (map frame, metres).

    Attributes
    ----------
    trajectory_xy : (k, 2) float
        The whole trajectory, thinned.
    lines : list of (int, (m, 2) float)
        Per strip, the trajectory while it was flown.
    coverage : MapRaster
        Strips covering each cell (0: none).
    control, check : list of (str, float, float)
        Control and check points: id, x, y.
    target : (xmin, ymin, xmax, ymax) or None
        The radiometric reference target.
    """

    trajectory_xy: np.ndarray
    lines: list[tuple[int, np.ndarray]]
    coverage: MapRaster
    control: list[tuple[str, float, float]] = field(default_factory=list)
    check: list[tuple[str, float, float]] = field(default_factory=list)
    target: tuple[float, float, float, float] | None = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """South-west and north-east corners of everything shown, with a margin."""
        left, right, bottom, top = self.coverage.extent()
        parts = [np.array([[left, bottom], [right, top]]), self.trajectory_xy]
        parts += [np.array([(x, y) for _, x, y in pts]) for pts in (self.control, self.check)
                  if pts]
        xy = np.concatenate(parts)
        lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
        margin = 0.03 * float(np.max(hi - lo))
        return lo - margin, hi + margin


@dataclass
class EvaluationSection:
    """``lidarcal evaluate``'s results (Tables 3 and 4 of the paper).

    Attributes
    ----------
    pairs : list of (int, int, RigidFit or None, RigidFit or None)
        Strip ids and the co-aligning transformation before and after.
    check : list of (str, list of int, float, float)
        Check point id, strips seeing it, residual before and after (m).
    source : str
        Computed for the report, or the file it was read from.
    """

    pairs: list[tuple[int, int, RigidFit | None, RigidFit | None]]
    check: list[tuple[str, list[int], float, float]]
    source: str

    def summary(self, state: str) -> AccuracySummary:
        """Check-point statistics ``before`` or ``after``."""
        k = 2 if state == "before" else 3
        return AccuracySummary.of(np.array([c[k] for c in self.check]))


@dataclass
class ReportContent:
    """Everything the HTML report shows.

    Attributes
    ----------
    title : str
    facts : list of (str, str)
        The summary's lines (label, value).
    calibration_facts : list of (str, str)
        The calibration's lines (file, sigma0, redundancy, ...).
    biases : list of BiasEntry
        The eight parameters in method.md order.
    correlation_names : list of str
        Estimated parameters, in the order of ``correlation``'s rows.
    correlation : (m, m) float64
    pairs : list of PairSection
    control : list of ControlResidual
        Metres, before and after.
    radiometry : RadiometrySection or None
        None where the clouds carry no intensity.
    strips : list of StripRow
    flight : FlightMap or None
    swath : SwathDifferences or None
    swath_limit_m : float
        Half-range of the dz colour scale, metres.
    quality : QualityAssessment or None
    evaluation : EvaluationSection or None
    provenance : Provenance or None
    crs : str
        The map frame's CRS as named on the axes ('' where not known).
    qa_warn_m, qa_error_m : float
        Thresholds of the pair QA, metres.
    smooth_slope_deg : float
        Steepest ground of the swath differences, degrees.
    warnings : list of str
    """

    title: str
    facts: list[tuple[str, str]]
    biases: list[BiasEntry]
    correlation_names: list[str]
    correlation: np.ndarray
    pairs: list[PairSection]
    control: list[ControlResidual]
    radiometry: RadiometrySection | None
    calibration_facts: list[tuple[str, str]] = field(default_factory=list)
    strips: list[StripRow] = field(default_factory=list)
    flight: FlightMap | None = None
    swath: SwathDifferences | None = None
    swath_limit_m: float = 0.16
    quality: QualityAssessment | None = None
    evaluation: EvaluationSection | None = None
    provenance: Provenance | None = None
    crs: str = ""
    qa_warn_m: float = 0.08
    qa_error_m: float = 0.16
    smooth_slope_deg: float = 10.0
    warnings: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------- HTML
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
             ("calibration", "Calibration"), ("swath", "Swath differences"),
             ("pairs", "Strip pairs"), ("evaluation", "Accuracy"),
             ("control", "Control points"), ("radiometry", "Radiometry"),
             ("provenance", "Provenance"))


def _esc(text: object) -> str:
    return html.escape(str(text))


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], numeric: set[int],
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


def _facts(pairs: Sequence[tuple[str, str]]) -> str:
    return _table([], [[_esc(k), _esc(v)] for k, v in pairs], set())


def _note(text: str) -> str:
    return f'<p class="note">{text}</p>'


class _Renderer:
    """Draws the figures one by one, saying how far it is."""

    def __init__(self, n_figures: int, progress: Progress | None) -> None:
        self.n = max(n_figures, 1)
        self.done = 0
        self.progress = progress

    def figure(self, fig_id: str, alt: str, fig: Figure, caption: str = "") -> str:
        """A ``<figure>`` holding ``fig`` as an embedded PNG."""
        if self.progress is not None:
            self.progress("drawing figures", self.done / self.n)
        img = (f'<img id="{html.escape(fig_id)}" class="figure" alt="{html.escape(alt)}" '
               f'src="data:image/png;base64,{figures.png_base64(fig)}">')
        self.done += 1
        cap = f"<figcaption>{caption}</figcaption>" if caption else ""
        return f"<figure>{img}{cap}</figure>"


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
    return ids


def render_html(content: ReportContent, *, progress: Progress | None = None) -> str:
    """The report as one HTML document (module docstring)."""
    draw = _Renderer(len(figure_ids(content)), progress)
    nav = "".join(f'<a href="#{key}">{_esc(name)}</a>' for key, name in _SECTIONS)
    parts = [f"<h1>{_esc(content.title)}</h1>", f"<nav>{nav}</nav>",
             _summary_html(content), _quality_html(content), _block_html(content, draw),
             _calibration_html(content, draw), _swath_html(content, draw),
             _pairs_html(content, draw), _evaluation_html(content.evaluation),
             _control_html(content.control), _radiometry_html(content, draw),
             _provenance_html(content.provenance)]
    body = "\n".join(parts)
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{_esc(content.title)}</title>\n<style>{_STYLE}</style>\n"
            f"<script>{_SCRIPT}</script>\n</head>\n<body>\n{body}\n</body>\n</html>\n")


def _section(key: str, title: str, inner: Sequence[str]) -> str:
    return f'<section id="{key}">\n<h2>{_esc(title)}</h2>\n' + "\n".join(inner) + \
        "\n</section>"


# ---------------------------------------------------------------------------- sections
def _summary_html(content: ReportContent) -> str:
    parts = []
    if content.quality is not None:
        parts.append(f'<p class="statement" id="ql-statement">'
                     f"{_esc(content.quality.statement())}</p>")
    parts.append(_facts(content.facts))
    parts.extend(f'<p class="WARN">warning: {_esc(w)}</p>' for w in content.warnings)
    return _section("summary", "Summary", parts)


def _quality_html(content: ReportContent) -> str:
    quality = content.quality
    if quality is None:
        return _section("quality", "Quality level (USGS Lidar Base Specification)",
                        ["<p>Not assessed: no swath differences.</p>"])
    header = ["measure", "measured", *(level.name for level in LBS_LEVELS), "how"]
    rows = []
    for c in quality.criteria:
        density = c.at_least
        value = (f"{c.value:.2f} /m&sup2;" if density else f"{format_cm(c.value)} cm") \
            if c.assessed else "not assessed"
        cells = [_esc(c.name), value]
        for level in LBS_LEVELS:
            limit = c.threshold(level)
            shown = f"&ge; {limit:g} /m&sup2;" if density else f"&le; {limit * 100:g} cm"
            met = c.met(level)
            mark = "" if met is None else (' <span class="met">met</span>' if met
                                           else ' <span class="missed">missed</span>')
            cells.append(shown + mark)
        cells.append(_esc(c.note))
        rows.append(cells)
    best = quality.best
    verdict = ["<tr><td><b>quality level</b></td><td></td>"]
    for level in LBS_LEVELS:
        ok = quality.met(level)
        verdict.append(f'<td><span class="{"met" if ok else "missed"}">'
                       f'{"met" if ok else "not met"}</span></td>')
    verdict.append(f"<td>best: {best.name if best else 'none'}</td></tr>")
    table = _table(header, rows, {1}).replace("</tbody>", "".join(verdict) + "</tbody>")
    return _section("quality", "Quality level (USGS Lidar Base Specification)", [
        f'<p class="statement">{_esc(quality.statement())}</p>', table,
        _note("Interswath measures: the height differences between overlapping strips after "
              "calibration, over smooth level ground (see Swath differences). A level is met "
              "when every assessed measure is within its threshold; QL1 and QL2 differ only "
              "in density. The pair QA of this report (OK/WARN/ERROR) uses the "
              f"configuration's qa.rmsdz_warn_m ({content.qa_warn_m * 100:g} cm) and "
              f"qa.max_difference_m ({content.qa_error_m * 100:g} cm). Intraswath "
              "smooth-surface precision is not assessed.")])


def _block_html(content: ReportContent, draw: _Renderer) -> str:
    parts = []
    crs = content.crs or "map frame (CRS not given: lidarcal report --crs names it)"
    if content.flight is not None:
        parts.append(draw.figure(
            "fig-flight-map", "flight lines, trajectory, control and check points",
            figures.flight_map_figure(content.flight, content.crs),
            f"Flight lines (the trajectory while each strip was flown, arrow: direction, "
            f"number: strip id) over the cells the strips cover; grey: the rest of the "
            f"trajectory. Coordinates: {_esc(crs)}."))
    if content.strips:
        rows = [[str(s.strip_id), str(s.points), _esc(s.start), f"{s.duration_s:.1f}",
                 f"{s.length_m:.0f}", f"{s.heading_deg:.1f}", f"{s.speed_mps:.1f}",
                 f"{s.height_m:.0f}", f"{s.density_per_m2:.2f}"] for s in content.strips]
        parts.append(_table(["strip", "points", "first point", "duration (s)", "length (m)",
                             "heading (deg)", "speed (m/s)", "height above ground (m)",
                             "density (/m&sup2;)"], rows, {1, 3, 4, 5, 6, 7, 8}))
        parts.append(_note("Heading: course over ground, degrees clockwise from grid north. "
                           "Height above ground: median trajectory height minus median "
                           "point height. Density: points over the area of the cells "
                           "holding the strip's points."))
    return _section("block", "Block: flight lines and strips", parts)


def _display(name: str, value: float) -> tuple[str, str]:
    """Value and unit as read by people (arcsec, cm, or a plain scale factor)."""
    shown, unit = display_value(name, value)
    return (f"{shown:+.3e}", "1") if name == "dS" else (f"{shown:+.2f}", unit)


def _bias_rows(biases: Sequence[BiasEntry]) -> list[list[str]]:
    rows = []
    for b in biases:
        value, unit = _display(b.name, b.value)
        sigma = _display(b.name, b.sigma)[0].lstrip("+") if b.sigma is not None else ""
        state = {"estimated": "estimated",
                 "fixed": "fixed (not solved for)"}.get(b.state, "not estimable")
        if b.reason:
            state += f": {_esc(b.reason)}"
        rows.append([_esc(b.name), value, sigma, unit, state])
    return rows


def _calibration_html(content: ReportContent, draw: _Renderer) -> str:
    parts = [_facts(content.calibration_facts),
             _table(["parameter", "estimate", "sigma", "unit", "status"],
                    _bias_rows(content.biases), {1, 2}),
             _note("A bias is the nominal value used by the system minus the true one; lever "
                   "arm in the body frame (right, forward, up), boresight angles about those "
                   "axes.")]
    if len(content.correlation_names) >= 2:
        parts.append(draw.figure(
            "fig-correlation", "correlation matrix of the estimated parameters",
            figures.correlation_figure(content.correlation_names, content.correlation),
            "Correlation coefficients of the estimated parameters (|r| above 0.9: the data "
            "hardly tell them apart)."))
    else:
        parts.append("<p>Fewer than two parameters estimated: no correlations.</p>")
    return _section("calibration", "Calibration", parts)


def _swath_html(content: ReportContent, draw: _Renderer) -> str:
    swath = content.swath
    title = "Swath differences: strip-to-strip heights over the block"
    if swath is None or not swath.pairs:
        return _section("swath", title, ["<p>No two strips share smooth ground.</p>"])
    before, after = swath.statistics("before"), swath.statistics("after")
    limit = content.swath_limit_m
    parts = [draw.figure(
        "fig-swath-dz", "block mosaics of strip-to-strip height differences before and after",
        figures.swath_figure(swath, limit, content.crs),
        f"Height difference dz between overlapping strips per {swath.grid.cell_m:.1f} m cell "
        f"of smooth ground, before and after calibration, on one colour scale of "
        f"&plusmn;{limit * 100:g} cm (qa.max_difference_m: darkest cells exceed it). Where "
        "more than two strips overlap, the two that differ most; later-flown minus "
        "earlier-flown.")]
    rows = []
    for p in swath.pairs:
        b, a = (DzStatistics.of(getattr(p, s)) for s in ("before", "after"))
        rows.append([f"{p.strips[0]} &amp; {p.strips[1]}", f"{p.later} &minus; {p.earlier}",
                     str(a.n_cells), format_cm(b.rmsdz), format_cm(a.rmsdz),
                     format_cm(b.max_abs), format_cm(a.max_abs)])
    rows.append(["<b>all</b>", "", str(after.n_cells), format_cm(before.rmsdz),
                 format_cm(after.rmsdz), format_cm(before.max_abs), format_cm(after.max_abs)])
    parts.append(_table(["strips", "dz", "cells", "RMSDz before (cm)", "RMSDz after (cm)",
                         "max |dz| before (cm)", "max |dz| after (cm)"], rows,
                        {2, 3, 4, 5, 6}))
    parts.append(_note(
        "Each strip's height per cell is the mean of its points there, each carried to the "
        "cell centre along its own surface normal. Smooth ground only: the strip has at least "
        "two points in the cell, every one with a trusted normal (no vegetation, edge or "
        f"wall) on a slope below {content.smooth_slope_deg:g} deg and at one height, and so "
        "do the neighbouring cells, without a step between them; elsewhere the cells are "
        "blank and not counted (pitched roofs, the surroundings of buildings, trees). "
        f"Coordinates: {_esc(content.crs or 'map frame')}."))
    return _section("swath", title, parts)


def _pairs_html(content: ReportContent, draw: _Renderer) -> str:
    title = "Strip pairs: normal discrepancies of the calibration's sample points"
    if not content.pairs:
        return _section("pairs", title, ["<p>No overlapping strip pairs.</p>"])
    rows = []
    for p in content.pairs:
        a, b = p.strips
        coverage = f"{p.coverage * 100:.0f}%" if p.coverage is not None else ""
        rows.append([f'<a href="#pair-{a}-{b}">{a} &amp; {b}</a>', coverage,
                     str(p.after.distance.size), format_cm(p.before.rms), format_cm(p.after.rms),
                     format_cm(p.after.p95), f'<span class="{p.qa_level}">{p.qa_level}</span>'])
    parts = [_table(["strips", "coverage", "points", "RMS before (cm)", "RMS after (cm)",
                     "95% after (cm)", "QA"], rows, {1, 2, 3, 4, 5}),
             _note("Signed distance of each sample point of the calibration from the other "
                   "strip's TIN patch along the patch normal; gross mismatches (walls, trees) "
                   "are left out of the RMS. QA of the RMS after: WARN above "
                   f"{content.qa_warn_m * 100:g} cm, ERROR above "
                   f"{content.qa_error_m * 100:g} cm. In the maps, before and after share one "
                   "colour scale (the 95th percentile of |discrepancy| before).")]
    for p in content.pairs:
        a, b = p.strips
        parts.append(f'<h3 id="pair-{a}-{b}">Strips {a} &amp; {b}</h3>')
        parts.append(draw.figure(f"fig-pair-{a}-{b}",
                                 f"normal discrepancies of strips {a} and {b} before and after",
                                 figures.pair_figure(p, content.crs)))
    return _section("pairs", title, parts)


def _fit_cells(fit: RigidFit | None) -> list[str]:
    """Shifts in cm, rotations in arcsec, '-' where undetermined; RMS and matches."""
    if fit is None:
        return ["no correspondences", *[""] * 7]
    arcsec = 180.0 / math.pi * 3600.0
    cells = []
    for i, name in enumerate(RIGID_NAMES):
        v = float(fit.values[i])
        if not fit.determined[i] or not math.isfinite(v):
            cells.append("-")
        else:
            cells.append(f"{v * (100.0 if name.startswith('t') else arcsec):+.1f}")
    cells += [f"{format_cm(fit.rms_before)} ({format_cm(fit.rms_after)})", str(fit.n_matches)]
    return cells


def _evaluation_html(section: EvaluationSection | None) -> str:
    title = "Accuracy: co-alignment of strip pairs and check points (lidarcal evaluate)"
    if section is None:
        return _section("evaluation", title, ["<p>Not evaluated.</p>"])
    parts = [f"<p>{_esc(section.source)}</p>", "<h3>Relative accuracy: rigid transformation "
             "co-aligning each strip pair (point-to-patch ICP)</h3>"]
    if section.pairs:
        rows = []
        for a, b, before, after in section.pairs:
            rows.append([f"{a} &amp; {b}", "before", *_fit_cells(before)])
            rows.append(["", "after", *_fit_cells(after)])
        parts.append(_table(["strips", "state", "tx (cm)", "ty (cm)", "tz (cm)",
                             "omega (\")", "phi (\")", "kappa (\")", "RMS cm (fitted)",
                             "matches"], rows, set(range(2, 10))))
        parts.append(_note("The transformation moving the first strip's points onto the "
                           "second strip's TIN: near zero after a good calibration. '-': not "
                           "determined by the overlap's shape (flat ground hides horizontal "
                           "shifts and the rotation about the vertical)."))
    else:
        parts.append("<p>No overlapping strip pairs.</p>")
    parts.append("<h3>Absolute accuracy: check points (strip surface minus surveyed "
                 "height)</h3>")
    if section.check:
        rows = [[_esc(pid), _esc(",".join(map(str, strips)) or "-"), format_cm(b, sign=True),
                 format_cm(a, sign=True)] for pid, strips, b, a in section.check]
        parts.append(_table(["check point", "strips", "before (cm)", "after (cm)"], rows,
                            {2, 3}))
        rows = []
        for state in ("before", "after"):
            s = section.summary(state)
            rows.append([state, str(s.n), format_cm(s.mean, sign=True), format_cm(s.std),
                         format_cm(s.rmse), format_cm(s.max_abs)])
        parts.append(_table(["state", "n", "mean (cm)", "std (cm)", "RMSE (cm)",
                             "max |r| (cm)"], rows, {1, 2, 3, 4, 5}))
    else:
        parts.append("<p>No check points (lidarcal report --check-points CSV).</p>")
    return _section("evaluation", title, parts)


def _control_html(control: Sequence[ControlResidual]) -> str:
    title = "Control points used by the calibration"
    if not control:
        return _section("control", title, ["<p>No control point falls on a strip.</p>"])
    rows = [[_esc(c.control_id), str(c.strip_id), format_cm(c.before, sign=True),
             format_cm(c.after, sign=True)] for c in control]
    return _section("control", title, [
        _table(["control point", "strip", "before (cm)", "after (cm)"], rows, {1, 2, 3}),
        _note("Signed normal distance of the control point from the strip's TIN patch, "
              "control minus strip; n/a: no patch within the threshold after correction.")])


def _radiometry_html(content: ReportContent, draw: _Renderer) -> str:
    section = content.radiometry
    title = "Radiometric correction"
    if section is None:
        return _section("radiometry", title,
                        ["<p>The clouds carry no intensity: no radiometric correction.</p>"])
    unit = "" if section.unit == "1" else " (intensity units)"
    rows = [[f"{c.lo_deg:.0f}-{c.hi_deg:.0f}", str(c.n_points), format_number(c.mean_intensity),
             format_number(c.vmr_intensity), format_number(c.mean_reflectance),
             format_number(c.vmr_reflectance),
             "n/a" if not math.isfinite(c.change) else f"{c.change * 100:+.1f}%"]
            for c in section.slope_classes]
    parts = [f'<p id="reflectance-meaning"><b>Reflectance</b>: {_esc(section.meaning)}</p>',
             _table(["slope (deg)", "points", "mean intensity", "VMR intensity",
                     f"mean reflectance{unit}", "VMR reflectance", "change"], rows,
                    {1, 2, 3, 4, 5, 6}),
             draw.figure("fig-vmr-slope",
                         "variance-to-mean ratio of intensity against slope, before and after",
                         figures.vmr_figure(section.slope_classes),
                         "Variance-to-mean ratio (VMR) of the recorded intensity and of the "
                         "reflectance per terrain-slope class (Habib et al. 2011, Fig. 5), the "
                         "reflectance put on the intensity's scale (one factor: equal means) so "
                         "that the two compare; the correction should lower it, most on gentle "
                         "slopes."),
             draw.figure("fig-reflectance-map", "map of intensity and reflectance",
                         figures.reflectance_figure(section.intensity, section.reflectance,
                                                    "reflectance (0-1)" if section.unit == "1"
                                                    else "relative reflectance "
                                                    "(intensity units)", content.crs),
                         "Mean recorded intensity and mean reflectance per cell, all strips; "
                         "grey scale from the 2nd to the 98th percentile, empty cells white.")]
    notes = [f"{section.n_used} of {section.n_points} points enter the slope statistics.",
             *section.notes]
    parts.append("".join(_note(_esc(n)) for n in notes))
    return _section("radiometry", title, parts)


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} B" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024  # type: ignore[assignment]
    return f"{n} B"  # pragma: no cover


def _provenance_html(provenance: Provenance | None) -> str:
    if provenance is None:
        return _section("provenance", "Provenance", ["<p>Not recorded.</p>"])
    facts = [("lidarcal", provenance.version), ("generated (UTC)", provenance.generated)]
    if provenance.command:
        facts.append(("command", provenance.command))
    facts.append(("flight configuration", provenance.configuration_source))
    rows = [[_esc(f.role), _esc(f.path), _size(f.size_bytes), f'<span class="mono">'
             f"{_esc(f.sha256)}</span>"] for f in provenance.inputs]
    changed = [(n, v) for n, v, c in provenance.configuration if c]
    config_rows = [[_esc(n), _esc(v)] for n, v, _ in provenance.configuration]
    classes = ["changed" if c else "" for _, _, c in provenance.configuration]
    return _section("provenance", "Provenance", [
        _facts(facts),
        "<h3>Inputs</h3>",
        _table(["input", "path", "size", "SHA-256"], rows, {2}),
        _note("The SHA-256 of a directory (a rosbag2 bag) is that of its files' names and "
              "contents in name order."),
        "<h3>Flight configuration</h3>",
        (f"<p>Differs from the defaults in: {_esc(', '.join(f'{n} = {v}' for n, v in changed))}"
         "</p>" if changed else "<p>All parameters at their defaults.</p>"),
        "<details><summary>every parameter</summary>"
        + _table(["parameter", "value"], config_rows, set(), row_classes=classes)
        + "</details>"])


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
    write_text(path, text, what="the report")
    logger.info("report written to %s (%d bytes)", path, len(text))
    return path
