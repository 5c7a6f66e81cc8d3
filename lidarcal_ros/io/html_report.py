"""The calibration report as one self-contained HTML file (``lidarcal report``).

What the report holds is described by :class:`ReportContent` (filled by
:mod:`lidarcal_ros.pipeline.report`); this module draws its figures with matplotlib's Agg
canvas (no pyplot, no display, no global state) and writes one HTML file in which every figure
is a base64 PNG ``<img>`` with an ``id`` and an ``alt`` text, and the style sheet and a small
script are inline: nothing is fetched, so the file reads offline and can be mailed as it is.

Sections: the facts of the run, the bias table (estimate, sigma, unit, or why a parameter was
not estimated), the correlation matrix as a heat map, per strip pair the normal discrepancies
over the overlap before and after calibration (two maps, each on a symmetric colour scale of
its own, and their histograms), the control-point residuals, the variance-to-mean ratio of
intensity against terrain slope before and after radiometric correction (the paper's Fig. 5),
and maps of raw intensity and reflectance.

The inline script marks every ``<img>`` that decoded (``data-rendered="1"``) and writes
``data-figures-total`` and ``data-figures-rendered`` on ``<body>`` once the page has loaded,
so a headless browser can tell that every figure rendered.

Map coordinates in the figures are map-frame metres relative to :attr:`ReportContent.origin`.
"""

from __future__ import annotations

import base64
import contextlib
import html
import io
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lidarcal_ros.core.calibrate import ControlResidual, PairDiscrepancies
from lidarcal_ros.core.params import display_value
from lidarcal_ros.errors import ConfigError

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

logger = logging.getLogger(__name__)

#: Resolution of the embedded PNG figures, dots per inch.
FIGURE_DPI = 90
#: Most points drawn per discrepancy map (a regular subsample beyond; statistics use all).
MAX_MAP_POINTS = 20_000


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
        ``OK``, ``WARN`` or ``ERROR`` for the RMS after (USGS LBS thresholds of the
        configuration).
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
        Variance-to-mean ratio of the recorded intensity and of the reflectance (intensity
        units: reflectance is normalised to the reference range), NaN for too few points.
    mean_intensity, mean_reflectance : float
        Means, intensity units.
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
    """A grid of mean values over the mission, rows from south to north.

    Attributes
    ----------
    values : (ny, nx) float64
        Mean per cell, NaN where no point fell.
    x0, y0 : float
        Map-frame coordinates of the south-west corner of cell ``[0, 0]``, metres.
    cell_m : float
        Cell size, metres.
    """

    values: np.ndarray
    x0: float
    y0: float
    cell_m: float

    def extent(self, origin: tuple[float, float]) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` relative to ``origin``, metres (for ``imshow``)."""
        ny, nx = self.values.shape
        left, bottom = self.x0 - origin[0], self.y0 - origin[1]
        return left, left + nx * self.cell_m, bottom, bottom + ny * self.cell_m


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
    notes : list of str
        Sentences shown under the figures (atmosphere used, points left out).
    """

    slope_classes: list[SlopeClass]
    intensity: MapRaster
    reflectance: MapRaster
    n_points: int
    n_used: int
    notes: list[str] = field(default_factory=list)


@dataclass
class ReportContent:
    """Everything the HTML report shows.

    Attributes
    ----------
    title : str
    facts : list of (str, str)
        Label and value of each line of the summary (bag, strips, sigma0, ...).
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
    origin : (float, float)
        Map-frame point the figures' coordinates are relative to, metres.
    qa_warn_m, qa_error_m : float
        RMS thresholds of the pair QA, metres.
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
    origin: tuple[float, float] = (0.0, 0.0)
    qa_warn_m: float = 0.08
    qa_error_m: float = 0.16
    warnings: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------- figures
def _new_figure(width_in: float, height_in: float, *, constrained: bool = True) -> Figure:
    """A figure on its own Agg canvas (no pyplot: no display, nothing global).

    ``constrained``: matplotlib's constrained layout, which costs about as much as drawing
    itself; without it the caller places the axes (the many pair figures do).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=FIGURE_DPI,
                 layout="constrained" if constrained else None)
    FigureCanvasAgg(fig)
    return fig


def _png_base64(fig: Figure) -> str:
    """The figure as a base64 PNG of 256 colours (a third of the size of true colour for the
    scatter maps, and no visible difference); no metadata."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    canvas = fig.canvas
    assert isinstance(canvas, FigureCanvasAgg), "figures come from _new_figure"
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    image = Image.fromarray(rgba).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT)
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", optimize=True)
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def _figure(fig_id: str, alt: str, fig: Figure, caption: str = "") -> str:
    """A ``<figure>`` holding ``fig`` as an embedded PNG."""
    img = (f'<img id="{html.escape(fig_id)}" class="figure" alt="{html.escape(alt)}" '
           f'src="data:image/png;base64,{_png_base64(fig)}">')
    cap = f"<figcaption>{caption}</figcaption>" if caption else ""
    return f"<figure>{img}{cap}</figure>"


def correlation_figure(names: Sequence[str], matrix: np.ndarray) -> Figure:
    """Heat map of the correlation matrix of the estimated parameters, values written in."""
    m = len(names)
    size = 1.2 + 0.55 * max(m, 2)
    fig = _new_figure(size + 1.0, size)
    ax = fig.add_subplot()
    image = ax.imshow(matrix, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(m), list(names), rotation=45, ha="right")
    ax.set_yticks(range(m), list(names))
    for i in range(m):
        for j in range(m):
            r = float(matrix[i, j])
            ax.text(j, i, f"{r:+.2f}", ha="center", va="center", fontsize=8,
                    color="white" if abs(r) > 0.6 else "black")
    fig.colorbar(image, ax=ax, shrink=0.8, label="correlation")
    return fig


def _symmetric_limit_cm(distance_m: np.ndarray) -> float:
    """Colour and histogram limit for discrepancies: their 95th percentile of ``|d|`` in cm,
    within 5..200 cm."""
    if not distance_m.size:
        return 5.0
    return float(np.clip(np.percentile(np.abs(distance_m), 95) * 100.0, 5.0, 200.0))


def _discrepancy_map(fig: Figure, ax: Axes, d: PairDiscrepancies,
                     origin: tuple[float, float], title: str) -> None:
    """Points coloured by their discrepancy (cm) on a symmetric scale of their own."""
    limit_cm = _symmetric_limit_cm(d.distance)
    step = max(1, d.distance.size // MAX_MAP_POINTS)
    xy = d.xy[::step]
    artist = ax.scatter(xy[:, 0] - origin[0], xy[:, 1] - origin[1],
                        c=d.distance[::step] * 100.0, s=2.0, cmap="RdBu_r",
                        vmin=-limit_cm, vmax=limit_cm, linewidths=0, rasterized=True)
    ax.set_aspect("equal", adjustable="box")
    ax.set_title(f"{title}: RMS {d.rms * 100:.1f} cm", fontsize=10)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.tick_params(labelsize=8)
    fig.colorbar(artist, ax=ax, shrink=0.9, pad=0.03, label="discrepancy (cm)")


def pair_figure(section: PairSection, origin: tuple[float, float]) -> Figure:
    """Normal discrepancies of one pair over the overlap, before and after (each map on its
    own symmetric colour scale), and their histograms (cm).

    An overlap wider than high gets its two maps one above the other, beside the histogram;
    otherwise the three panels stand side by side.
    """
    before, after = section.before, section.after
    xy = after.xy if after.xy.shape[0] else before.xy
    span = np.ptp(xy, axis=0) if xy.shape[0] else np.ones(2)
    aspect = float(np.clip(span[1] / max(float(span[0]), 1e-3), 0.15, 4.0))  # height / width
    if aspect < 1.0:
        map_width_in = 5.4
        fig = _new_figure(13.0, 2 * (map_width_in * aspect + 0.9) + 0.7, constrained=False)
        grid = fig.add_gridspec(2, 2, width_ratios=(1.7, 1.0), left=0.05, right=0.98,
                                bottom=0.09, top=0.9, hspace=0.45, wspace=0.12)
        ax_before, ax_after = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0])
        ax_hist = fig.add_subplot(grid[:, 1])
    else:
        map_width_in = 3.6
        fig = _new_figure(13.0, float(np.clip(map_width_in * aspect + 1.5, 4.0, 10.0)),
                          constrained=False)
        grid = fig.add_gridspec(1, 3, width_ratios=(1.0, 1.0, 1.1), left=0.05, right=0.98,
                                bottom=0.12, top=0.86, wspace=0.3)
        ax_before, ax_after, ax_hist = (fig.add_subplot(grid[0, k]) for k in range(3))
    _discrepancy_map(fig, ax_before, before, origin, "before")
    _discrepancy_map(fig, ax_after, after, origin, "after")
    limit_cm = _symmetric_limit_cm(before.distance)
    bins = np.linspace(-limit_cm, limit_cm, 61).tolist()
    for d, label, color in ((before, "before", "tab:red"), (after, "after", "tab:blue")):
        values = np.clip(d.distance * 100.0, -limit_cm, limit_cm)
        ax_hist.hist(values, bins=bins, histtype="stepfilled", alpha=0.45, color=color,
                     label=f"{label}: RMS {d.rms * 100:.1f} cm, n {d.distance.size}")
    ax_hist.set_xlabel("normal discrepancy (cm; clipped at the ends)")
    ax_hist.set_ylabel("points")
    ax_hist.legend(fontsize=8, loc="upper left")
    ax_hist.tick_params(labelsize=8)
    a, b = section.strips
    fig.suptitle(f"strips {a} & {b}: points of strip {after.points_strip} on the TIN of "
                 f"strip {after.tin_strip}", fontsize=11)
    return fig


def vmr_figure(classes: Sequence[SlopeClass]) -> Figure:
    """Variance-to-mean ratio of intensity per slope class before and after radiometric
    correction, and its relative change (the paper's Fig. 5)."""
    fig = _new_figure(11.0, 4.0)
    ax_vmr, ax_change = fig.subplots(1, 2)
    labels = [f"{c.lo_deg:.0f}-{c.hi_deg:.0f}" for c in classes]
    pos = np.arange(len(classes))
    ax_vmr.bar(pos - 0.2, [c.vmr_intensity for c in classes], width=0.4,
               label="intensity (before)", color="tab:red")
    ax_vmr.bar(pos + 0.2, [c.vmr_reflectance for c in classes], width=0.4,
               label="reflectance (after)", color="tab:blue")
    ax_vmr.set_xticks(pos, labels)
    ax_vmr.set_xlabel("terrain slope (deg)")
    ax_vmr.set_ylabel("variance / mean (intensity units)")
    ax_vmr.legend(fontsize=8)
    change = np.array([c.change * 100.0 for c in classes])
    colors = ["tab:green" if v < 0 else "tab:orange" for v in np.nan_to_num(change)]
    ax_change.bar(pos, np.nan_to_num(change), color=colors)
    ax_change.axhline(0.0, color="black", linewidth=0.8)
    ax_change.set_xticks(pos, labels)
    ax_change.set_xlabel("terrain slope (deg)")
    ax_change.set_ylabel("change of variance / mean (%)")
    for axis in (ax_vmr, ax_change):
        axis.tick_params(labelsize=8)
    return fig


def _robust_limits(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if not finite.size:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [2.0, 98.0])
    return float(lo), float(max(hi, lo + 1e-6))


def reflectance_figure(section: RadiometrySection, origin: tuple[float, float]) -> Figure:
    """Maps of the mean recorded intensity and the mean reflectance per cell (side by side,
    or one above the other for a mission much wider than high)."""
    ny, nx = section.reflectance.values.shape
    aspect = ny / max(nx, 1)
    if aspect < 0.6:
        fig = _new_figure(12.0, float(np.clip(2 * 9.5 * aspect + 2.0, 4.0, 12.5)))
        axes = fig.subplots(2, 1)
    else:
        fig = _new_figure(12.0, float(np.clip(5.0 * aspect + 1.2, 3.0, 9.0)))
        axes = fig.subplots(1, 2)
    for ax, raster, label in ((axes[0], section.intensity, "intensity (recorded)"),
                              (axes[1], section.reflectance, "reflectance")):
        vmin, vmax = _robust_limits(raster.values)
        image = ax.imshow(raster.values, origin="lower", extent=raster.extent(origin),
                          cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(f"{label}, {raster.cell_m:.1f} m cells", fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.tick_params(labelsize=8)
        fig.colorbar(image, ax=ax, shrink=0.9, label="intensity units")
    return fig


# ---------------------------------------------------------------------------- HTML
_STYLE = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1250px; color: #222;
       line-height: 1.4; padding: 0 1em; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.8em;
     border-bottom: 1px solid #ccc; } h3 { font-size: 1.0em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; }
th { background: #f2f2f2; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
figure { margin: 0.8em 0; } figure img { max-width: 100%; height: auto; }
figcaption { font-size: 0.9em; color: #555; }
.OK { color: #1a7f37; font-weight: bold; } .WARN { color: #9a6700; font-weight: bold; }
.ERROR { color: #cf222e; font-weight: bold; } .note { color: #555; font-size: 0.9em; }
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


def _esc(text: object) -> str:
    return html.escape(str(text))


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], numeric: set[int]) -> str:
    """An HTML table (no header row for an empty ``header``); cells are HTML already
    (escape before); columns in ``numeric`` right aligned."""
    head = "<thead><tr>" + "".join(f"<th>{h}</th>" for h in header) + "</tr></thead>" \
        if header else ""
    body = "".join(
        "<tr>" + "".join(f'<td class="num">{c}</td>' if i in numeric else f"<td>{c}</td>"
                         for i, c in enumerate(row)) + "</tr>"
        for row in rows)
    return f"<table>{head}<tbody>{body}</tbody></table>"


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


def _cm(value: float, sign: bool = False) -> str:
    if not math.isfinite(value):
        return "n/a"
    return f"{value * 100:+.1f}" if sign else f"{value * 100:.1f}"


def render_html(content: ReportContent) -> str:
    """The report as one HTML document (module docstring)."""
    parts = [f"<h1>{_esc(content.title)}</h1>"]
    parts.append(_table([], [[_esc(k), _esc(v)] for k, v in content.facts], set()))
    for w in content.warnings:
        parts.append(f'<p class="WARN">warning: {_esc(w)}</p>')
    parts.append("<h2>System biases</h2>")
    parts.append(_table(["parameter", "estimate", "sigma", "unit", "status"],
                        _bias_rows(content.biases), {1, 2}))
    parts.append('<p class="note">A bias is the nominal value used by the system minus '
                 "the true one; lever arm in the body frame (right, forward, up), "
                 "boresight angles about those axes.</p>")
    parts.append("<h2>Correlations of the estimates</h2>")
    if len(content.correlation_names) >= 2:
        parts.append(_figure(
            "fig-correlation", "correlation matrix of the estimated parameters",
            correlation_figure(content.correlation_names, content.correlation),
            "Correlation coefficients of the estimated parameters (|r| above 0.9: the "
            "data hardly tell them apart)."))
    else:
        parts.append("<p>Fewer than two parameters estimated: no correlations.</p>")
    parts.append(_pairs_html(content))
    parts.append(_control_html(content.control))
    parts.append(_radiometry_html(content.radiometry, content.origin))
    body = "\n".join(parts)
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{_esc(content.title)}</title>\n<style>{_STYLE}</style>\n"
            f"<script>{_SCRIPT}</script>\n</head>\n<body>\n{body}\n</body>\n</html>\n")


def _pairs_html(content: ReportContent) -> str:
    parts = ["<h2>Strip pairs: normal discrepancies before and after</h2>"]
    if not content.pairs:
        parts.append("<p>No overlapping strip pairs.</p>")
        return "\n".join(parts)
    rows = []
    for p in content.pairs:
        a, b = p.strips
        coverage = f"{p.coverage * 100:.0f}%" if p.coverage is not None else ""
        rows.append([f"{a} &amp; {b}", coverage, str(p.after.distance.size),
                     _cm(p.before.rms), _cm(p.after.rms), _cm(p.after.p95),
                     f'<span class="{p.qa_level}">{p.qa_level}</span>'])
    parts.append(_table(["strips", "coverage", "points", "RMS before (cm)", "RMS after (cm)",
                         "95% after (cm)", "QA"], rows, {1, 2, 3, 4, 5}))
    parts.append(f'<p class="note">Signed distance of each sample point from the other '
                 f"strip's TIN patch along the patch normal; gross mismatches (walls, trees) "
                 f"are left out of the RMS. QA of the RMS after: WARN above "
                 f"{content.qa_warn_m * 100:.0f} cm, ERROR above "
                 f"{content.qa_error_m * 100:.0f} cm. Map coordinates relative to "
                 f"({content.origin[0]:.0f}, {content.origin[1]:.0f}) m.</p>")
    for p in content.pairs:
        a, b = p.strips
        parts.append(f"<h3>Strips {a} &amp; {b}</h3>")
        parts.append(_figure(f"fig-pair-{a}-{b}",
                             f"normal discrepancies of strips {a} and {b} before and after",
                             pair_figure(p, content.origin)))
    return "\n".join(parts)


def _control_html(control: Sequence[ControlResidual]) -> str:
    parts = ["<h2>Control points</h2>"]
    if not control:
        parts.append("<p>No control point falls on a strip.</p>")
        return "\n".join(parts)
    rows = [[_esc(c.control_id), str(c.strip_id), _cm(c.before, True), _cm(c.after, True)]
            for c in control]
    parts.append(_table(["control point", "strip", "before (cm)", "after (cm)"], rows,
                        {1, 2, 3}))
    parts.append('<p class="note">Signed normal distance of the control point from the '
                 "strip's TIN patch, control minus strip; n/a: no patch within the threshold "
                 "after correction.</p>")
    return "\n".join(parts)


def _radiometry_html(section: RadiometrySection | None, origin: tuple[float, float]) -> str:
    parts = ["<h2>Radiometric correction</h2>"]
    if section is None:
        parts.append("<p>The clouds carry no intensity: no radiometric correction.</p>")
        return "\n".join(parts)
    rows = [[f"{c.lo_deg:.0f}-{c.hi_deg:.0f}", str(c.n_points), _num(c.mean_intensity),
             _num(c.vmr_intensity), _num(c.mean_reflectance), _num(c.vmr_reflectance),
             "n/a" if not math.isfinite(c.change) else f"{c.change * 100:+.1f}%"]
            for c in section.slope_classes]
    parts.append(_table(["slope (deg)", "points", "mean intensity", "VMR intensity",
                         "mean reflectance", "VMR reflectance", "change"], rows,
                        {1, 2, 3, 4, 5, 6}))
    parts.append(_figure(
        "fig-vmr-slope", "variance-to-mean ratio of intensity against slope, before and after",
        vmr_figure(section.slope_classes),
        "Variance-to-mean ratio (VMR) of the recorded intensity and of the reflectance per "
        "terrain-slope class (Habib et al. 2011, Fig. 5): the radiometric correction should "
        "lower it, most on gentle slopes."))
    parts.append(_figure("fig-reflectance-map", "map of intensity and reflectance",
                         reflectance_figure(section, origin),
                         "Mean recorded intensity and mean reflectance per cell, all "
                         "strips; grey scale from the 2nd to the 98th percentile, empty "
                         "cells white."))
    notes = [f"{section.n_used} of {section.n_points} points enter the slope statistics.",
             *section.notes]
    parts.append("".join(f'<p class="note">{_esc(n)}</p>' for n in notes))
    return "\n".join(parts)


def _num(value: float) -> str:
    return f"{value:.4g}" if math.isfinite(value) else "n/a"


def write_html_report(path: str | Path, content: ReportContent, *,
                      overwrite: bool = False) -> Path:
    """Render ``content`` and write it to ``path`` (atomically: a reader never sees half a
    file).

    Raises
    ------
    ConfigError
        ``path`` exists and ``overwrite`` is False, or it cannot be written.
    """
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise ConfigError(f"{path}: exists (use --overwrite to replace it)")
    text = render_html(content)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise ConfigError(f"{path}: cannot write the report ({exc.strerror or exc})") from None
    logger.info("report written to %s (%d bytes)", path, len(text))
    return path
