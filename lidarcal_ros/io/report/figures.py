"""The figures of the HTML report, drawn with matplotlib's Agg canvas and encoded as PNG.

Map-frame coordinates; before and after share one colour scale.
"""

from __future__ import annotations

import base64
import io
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from lidarcal_ros.core.units import format_cm

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from lidarcal_ros.core.calibration.result import PairDiscrepancies
    from lidarcal_ros.core.qa.swath_differences import SwathDifferences
    from lidarcal_ros.io.report.content import (
        FlightMap,
        MapRaster,
        PairSection,
        SlopeClass,
        TrajectorySection,
    )

#: Resolution of the embedded PNG figures, dots per inch.
FIGURE_DPI = 90
#: Diverging colour map of signed differences (blue below, red above).
DIFFERENCE_CMAP = "RdBu_r"
#: Pair maps: cells hold this many matched points on average.
PAIR_POINTS_PER_CELL = 4.0
_SMALL = 8


def new_figure(width_in: float, height_in: float, *, constrained: bool = False) -> Figure:
    """A figure on its own Agg canvas (no pyplot: no display, nothing global).

    ``constrained``: matplotlib's constrained layout (about as costly as drawing itself;
    the many pair figures place their axes by hand).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=FIGURE_DPI,
                 layout="constrained" if constrained else None)
    FigureCanvasAgg(fig)
    return fig


def png_base64(fig: Figure) -> str:
    """The figure as a base64 PNG of at most 256 colours (a third of the size of true colour
    and no visible difference); no metadata."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    canvas = fig.canvas
    assert isinstance(canvas, FigureCanvasAgg), "figures come from new_figure"
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    # The octree quantiser: a fifth of the time of the median cut and smaller files; it
    # renders white as (254, 254, 254), so the background's palette entry is set back to the
    # figure's white (the pixels sharing it are as near white).
    image = Image.fromarray(rgba).convert("RGB").quantize(
        256, method=Image.Quantize.FASTOCTREE)
    palette = image.getpalette() or []
    corner = image.getpixel((0, 0))
    if isinstance(corner, int) and len(palette) >= 3 * (corner + 1):
        palette[3 * corner:3 * corner + 3] = [255, 255, 255]
        image.putpalette(palette)
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", compress_level=6)
    return base64.b64encode(buffer.getvalue()).decode("ascii")


# ---------------------------------------------------------------------------- map axes
def _map_axes(ax: Axes, crs: str, *, labels: bool = True) -> None:
    """Equal aspect, plain map coordinates (no offset, few ticks, y ticks upright)."""
    from matplotlib.ticker import MaxNLocator, ScalarFormatter

    ax.set_aspect("equal", adjustable="box")
    for axis in (ax.xaxis, ax.yaxis):
        formatter = ScalarFormatter(useOffset=False)
        formatter.set_scientific(False)
        axis.set_major_formatter(formatter)
        axis.set_major_locator(MaxNLocator(nbins=4))
    ax.tick_params(labelsize=7)
    for label in ax.get_yticklabels():
        label.set_rotation(90)
        label.set_verticalalignment("center")
    if labels:
        ax.set_xlabel(f"easting (m){', ' + crs if crs else ''}", fontsize=_SMALL)
        ax.set_ylabel("northing (m)", fontsize=_SMALL)


def _raster(ax: Axes, raster: MapRaster, **kwargs: Any) -> Any:
    return ax.imshow(raster.values, origin="lower", extent=raster.extent(),
                     interpolation="nearest", **kwargs)


# ---------------------------------------------------------------------------- figures
def correlation_figure(names: Sequence[str], matrix: np.ndarray) -> Figure:
    """Heat map of the correlation matrix of the estimated parameters, values written in."""
    m = len(names)
    size = 1.2 + 0.5 * max(m, 2)
    fig = new_figure(size + 1.2, size, constrained=True)
    ax = fig.add_subplot()
    image = ax.imshow(matrix, cmap=DIFFERENCE_CMAP, vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(m), list(names), rotation=45, ha="right")
    ax.set_yticks(range(m), list(names))
    for i in range(m):
        for j in range(m):
            r = float(matrix[i, j])
            ax.text(j, i, f"{r:+.2f}", ha="center", va="center", fontsize=7,
                    color="white" if abs(r) > 0.6 else "black")
    fig.colorbar(image, ax=ax, shrink=0.8, label="correlation")
    return fig


def flight_map_figure(flight: FlightMap, crs: str) -> Figure:
    """The block: strip coverage, the trajectory (grey: turns), each strip's line with its
    direction and id, control and check points, the reference target."""
    from matplotlib.patches import Rectangle

    lo, hi = flight.bounds()
    span = np.maximum(hi - lo, 1.0)
    aspect = float(np.clip(span[1] / span[0], 0.3, 2.0))
    fig = new_figure(9.5, float(np.clip(7.0 * aspect + 1.0, 3.5, 12.0)), constrained=True)
    ax = fig.add_subplot()
    coverage = np.where(flight.coverage.values > 0, flight.coverage.values, np.nan)
    top = int(np.nanmax(coverage)) if np.isfinite(coverage).any() else 1
    image = ax.imshow(coverage, origin="lower", extent=flight.coverage.extent(),
                      cmap="Greens", vmin=0.5, vmax=top + 0.5, interpolation="nearest",
                      alpha=0.6)
    colorbar = fig.colorbar(image, ax=ax, shrink=0.6, pad=0.02,
                            ticks=range(1, top + 1, max(1, top // 8)))
    colorbar.set_label("strips covering", fontsize=_SMALL)
    colorbar.ax.tick_params(labelsize=7)
    t = flight.trajectory_xy
    ax.plot(t[:, 0], t[:, 1], color="0.6", linewidth=0.8, label="trajectory")
    # Lines flown along one track (at two heights, or twice) share one label.
    labels: list[tuple[np.ndarray, list[str], str]] = []
    for k, (strip_id, xy) in enumerate(flight.lines):
        if xy.shape[0] < 2:
            continue
        colour = f"C{k % 10}"
        ax.plot(xy[:, 0], xy[:, 1], color=colour, linewidth=2.0)
        ax.annotate("", xy=xy[-1], xytext=xy[max(len(xy) - 3, 0)],
                    arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 2.0})
        near = next((lab for lab in labels
                     if np.hypot(*(lab[0] - xy[0])) < 0.02 * float(span.max())), None)
        if near is None:
            labels.append((xy[0], [str(strip_id)], colour))
        else:
            near[1].append(str(strip_id))
    for start, ids, colour in labels:
        ax.annotate(", ".join(ids), xy=(float(start[0]), float(start[1])), fontsize=9,
                    fontweight="bold", color=colour if len(ids) == 1 else "black", xytext=(-4, -4),
                    textcoords="offset points", ha="right", va="top")
    for points, marker, colour, label in ((flight.control, "^", "tab:red", "control points"),
                                          (flight.check, "o", "tab:blue", "check points")):
        if not points:
            continue
        xy = np.array([(x, y) for _, x, y in points])
        ax.scatter(xy[:, 0], xy[:, 1], marker=marker, s=40, color=colour, edgecolor="black",
                   linewidths=0.5, zorder=5, label=label)
        for name, x, y in points:
            ax.annotate(name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7)
    if flight.target is not None:
        x0, y0, x1, y1 = flight.target
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="tab:purple",
                               linewidth=1.5, label="reference target"))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    _map_axes(ax, crs)
    fig.legend(fontsize=7, loc="outside lower center", ncols=4, frameon=False)
    return fig


def _difference_maps(fig: Figure, axes: Sequence[Axes], rasters: Sequence[np.ndarray],
                     extent: tuple[float, float, float, float], titles: Sequence[str],
                     limit_cm: float, crs: str, cbar_ax: Axes) -> None:
    """Signed differences (cm) on one symmetric scale in every panel, one colour bar."""
    image = None
    for ax, values, title in zip(axes, rasters, titles):
        image = ax.imshow(values * 100.0, origin="lower", extent=extent,
                          interpolation="nearest", cmap=DIFFERENCE_CMAP, vmin=-limit_cm,
                          vmax=limit_cm)
        ax.set_title(title, fontsize=9)
        _map_axes(ax, crs)
    assert image is not None
    colorbar = fig.colorbar(image, cax=cbar_ax, extend="both")
    colorbar.set_label("dz (cm)", fontsize=_SMALL)
    colorbar.ax.tick_params(labelsize=7)


def _histograms(ax: Axes, series: Sequence[tuple[np.ndarray, str, str]], limit_cm: float,
                xlabel: str) -> None:
    """Histograms (cm; values beyond the limit gathered in the end bins), log counts."""
    bins = np.linspace(-limit_cm, limit_cm, 61).tolist()
    for values, label, colour in series:
        if not values.size:
            continue
        clipped = np.clip(values * 100.0, -limit_cm, limit_cm)
        ax.hist(clipped, bins=bins, histtype="stepfilled", alpha=0.45, color=colour,
                label=label)
    ax.set_xlabel(xlabel, fontsize=_SMALL)
    ax.set_ylabel("cells" if "dz" in xlabel else "points", fontsize=_SMALL)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="upper left")


def _side_by_side(fig: Figure, aspect: float) -> tuple[Axes, Axes, Axes, Axes]:
    """Two maps, a colour bar and a histogram: one row when the maps are not much wider
    than high, else the maps one above the other beside the histogram (an empty column
    keeps the colour bar's label clear of the histogram's)."""
    if aspect >= 0.55:
        grid = fig.add_gridspec(1, 5, width_ratios=(1.0, 1.0, 0.05, 0.22, 1.0), left=0.05,
                                right=0.98, bottom=0.16, top=0.86, wspace=0.25)
        return (fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1]),
                fig.add_subplot(grid[0, 2]), fig.add_subplot(grid[0, 4]))
    grid = fig.add_gridspec(2, 4, width_ratios=(1.0, 0.03, 0.12, 0.55), left=0.06, right=0.98,
                            bottom=0.1, top=0.9, hspace=0.5, wspace=0.15)
    return (fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0]),
            fig.add_subplot(grid[:, 1]), fig.add_subplot(grid[:, 3]))


def _figure_size(aspect: float) -> tuple[float, float]:
    """(width, height) in inches for :func:`_side_by_side` maps of height/width ``aspect``."""
    if aspect >= 0.55:
        return 13.0, float(np.clip(3.2 * aspect + 1.5, 3.6, 5.0))
    return 13.0, float(np.clip(2 * 7.4 * aspect + 2.2, 3.6, 8.0))


def swath_figure(swath: SwathDifferences, limit_m: float, crs: str) -> Figure:
    """The block mosaics of dz before and after calibration on one symmetric scale
    (``+-limit_m``): side by side (one above the other for a block much wider than high),
    and below them the histograms of every pair's dz."""
    grid = swath.grid
    # The maps show the cells that hold a difference (with a margin of a few cells).
    held = np.isfinite(swath.before) | np.isfinite(swath.after)
    rows, cols = (np.flatnonzero(held.any(axis=a)) for a in (1, 0))
    if not rows.size:
        rows, cols = np.arange(grid.ny), np.arange(grid.nx)
    r0, r1 = max(int(rows[0]) - 3, 0), min(int(rows[-1]) + 4, grid.ny)
    c0, c1 = max(int(cols[0]) - 3, 0), min(int(cols[-1]) + 4, grid.nx)
    extent = (grid.x0 + c0 * grid.cell_m, grid.x0 + c1 * grid.cell_m,
              grid.y0 + r0 * grid.cell_m, grid.y0 + r1 * grid.cell_m)
    aspect = (r1 - r0) / max(c1 - c0, 1)
    if aspect >= 0.55:
        map_h = float(np.clip(5.4 * aspect, 2.5, 9.0))
        fig = new_figure(13.0, map_h + 3.6)
        spec = fig.add_gridspec(2, 3, width_ratios=(1.0, 1.0, 0.04),
                                height_ratios=(map_h, 2.0), left=0.07, right=0.93,
                                bottom=0.08, top=0.95, hspace=0.35, wspace=0.2)
        ax_before, ax_after = fig.add_subplot(spec[0, 0]), fig.add_subplot(spec[0, 1])
        cbar, ax_hist = fig.add_subplot(spec[0, 2]), fig.add_subplot(spec[1, :2])
    else:
        map_h = float(np.clip(11.0 * aspect, 1.2, 6.0))
        fig = new_figure(13.0, 2 * map_h + 4.2)
        spec = fig.add_gridspec(3, 2, width_ratios=(1.0, 0.02),
                                height_ratios=(map_h, map_h, 2.0), left=0.07, right=0.93,
                                bottom=0.07, top=0.96, hspace=0.45, wspace=0.05)
        ax_before, ax_after = fig.add_subplot(spec[0, 0]), fig.add_subplot(spec[1, 0])
        cbar, ax_hist = fig.add_subplot(spec[:2, 1]), fig.add_subplot(spec[2, 0])
    before, after = (swath.statistics(s) for s in ("before", "after"))
    limit_cm = limit_m * 100.0
    _difference_maps(fig, (ax_before, ax_after), (swath.before[r0:r1, c0:c1],
                                                 swath.after[r0:r1, c0:c1]), extent,
                     (f"before calibration: RMSDz {format_cm(before.rmsdz)} cm",
                      f"after calibration: RMSDz {format_cm(after.rmsdz)} cm"), limit_cm, crs, cbar)
    values = {s: np.concatenate([getattr(p, s) for p in swath.pairs]) if swath.pairs
              else np.zeros(0) for s in ("before", "after")}
    _histograms(ax_hist, ((values["before"], f"before, {before.n_cells} cells", "tab:red"),
                          (values["after"], f"after, {after.n_cells} cells", "tab:blue")),
                limit_cm, "dz of every strip pair (cm; beyond the scale in the end bins)")
    ax_hist.set_yscale("log")
    return fig


def _pair_raster(d: PairDiscrepancies, x0: float, y0: float, cell: float,
                 shape: tuple[int, int]) -> np.ndarray:
    """Mean discrepancy per cell (m; NaN where no point)."""
    ny, nx = shape
    col = np.clip(((d.xy[:, 0] - x0) / cell).astype(np.int64), 0, nx - 1)
    row = np.clip(((d.xy[:, 1] - y0) / cell).astype(np.int64), 0, ny - 1)
    key = row * nx + col
    sums = np.bincount(key, weights=d.distance, minlength=nx * ny)
    counts = np.bincount(key, minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan).reshape(ny, nx)


def pair_limit_cm(before: np.ndarray) -> float:
    """Colour and histogram limit of a pair: the 95th percentile of ``|d|`` before
    calibration in cm, within 5..200 cm (both states are drawn on it)."""
    if not before.size:
        return 5.0
    return float(np.clip(np.percentile(np.abs(before), 95) * 100.0, 5.0, 200.0))


def pair_figure(section: PairSection, crs: str) -> Figure:
    """Normal discrepancies of one pair over the overlap, before and after on one symmetric
    scale (mean per cell of a few points), and their histograms (cm)."""
    before, after = section.before, section.after
    both = np.concatenate([before.xy, after.xy]) if before.xy.size or after.xy.size \
        else np.zeros((1, 2))
    lo, hi = both.min(axis=0), both.max(axis=0)
    span = np.maximum(hi - lo, 1.0)
    n = max(before.distance.size, after.distance.size, 1)
    cell = max(math.sqrt(float(span[0] * span[1]) * PAIR_POINTS_PER_CELL / n), 0.5)
    shape = (int(span[1] // cell) + 1, int(span[0] // cell) + 1)
    aspect = float(np.clip(span[1] / span[0], 0.15, 4.0))
    fig = new_figure(*_figure_size(aspect))
    ax_before, ax_after, cbar, ax_hist = _side_by_side(fig, aspect)
    limit_cm = pair_limit_cm(before.distance)
    extent = (float(lo[0]), float(lo[0] + shape[1] * cell), float(lo[1]),
              float(lo[1] + shape[0] * cell))
    rasters = [_pair_raster(d, float(lo[0]), float(lo[1]), cell, shape) for d in (before, after)]
    _difference_maps(fig, (ax_before, ax_after), rasters, extent,
                     (f"before: RMS {format_cm(before.rms)} cm",
                      f"after: RMS {format_cm(after.rms)} cm"),
                     limit_cm, crs, cbar)
    cbar.set_ylabel("normal discrepancy (cm)", fontsize=_SMALL)
    _histograms(ax_hist, ((before.distance, f"before, {before.distance.size} points",
                           "tab:red"),
                          (after.distance, f"after, {after.distance.size} points", "tab:blue")),
                limit_cm, "normal discrepancy (cm; beyond the scale in the end bins)")
    a, b = section.strips
    fig.suptitle(f"strips {a} & {b}: points of strip {after.points_strip} on the TIN of "
                 f"strip {after.tin_strip}, mean per {cell:.1f} m cell", fontsize=10)
    return fig


#: Samples of each strip's error curve in the trajectory figure.
TRAJECTORY_CURVE_SAMPLES = 100


def trajectory_figure(section: TrajectorySection) -> Figure:
    """Each strip's estimated trajectory error ``e_s(t)`` (E, N, U; cm) over the time its
    points were flown, with the band of one sigma about it, one panel per axis."""
    fig = new_figure(11.0, 6.8, constrained=True)
    axes = fig.subplots(3, 1, sharex=True)
    estimate = section.estimate
    for k, sid in enumerate(sorted(estimate.strips)):
        se = estimate.strips[sid]
        lo, hi = section.spans.get(sid, (se.t_ref, se.t_ref))
        t = np.linspace(lo, hi, TRAJECTORY_CURVE_SAMPLES if hi > lo else 1)
        e, s = se.error(t) * 100.0, se.sigma_at(t) * 100.0
        x = t - section.t0
        colour = f"C{k % 10}"
        for axis, ax in enumerate(axes):
            if x.size > 1:
                ax.plot(x, e[:, axis], color=colour, linewidth=1.5)
            else:  # (a strip of the file the mission does not hold: its t_ref)
                ax.plot(x, e[:, axis], "o", color=colour, markersize=4)
            if np.isfinite(s[:, axis]).all():
                ax.fill_between(x, e[:, axis] - s[:, axis], e[:, axis] + s[:, axis],
                                color=colour, alpha=0.2, linewidth=0)
        axes[0].annotate(str(sid), (float(x[len(x) // 2]), 1.0), xycoords=("data", "axes fraction"),
                         xytext=(0, 2), textcoords="offset points", ha="center", va="bottom",
                         fontsize=8, fontweight="bold", color=colour)
    for ax, name in zip(axes, ("E (x)", "N (y)", "U (z)"), strict=True):
        ax.axhline(0.0, color="black", linewidth=0.6)
        ax.set_ylabel(f"{name} error (cm)", fontsize=_SMALL)
        ax.tick_params(labelsize=7)
        ax.grid(True, linewidth=0.3, alpha=0.5)
    axes[-1].set_xlabel(f"time since {section.start} (s)", fontsize=_SMALL)
    return fig


def vmr_figure(classes: Sequence[SlopeClass]) -> Figure:
    """Variance-to-mean ratio of intensity and of reflectance (on the intensity's scale) per
    slope class, and its relative change (the paper's Fig. 5)."""
    fig = new_figure(11.0, 3.8, constrained=True)
    ax_vmr, ax_change = fig.subplots(1, 2)
    labels = [f"{c.lo_deg:.0f}-{c.hi_deg:.0f}" for c in classes]
    pos = np.arange(len(classes))
    ax_vmr.bar(pos - 0.2, [c.vmr_intensity for c in classes], width=0.4,
               label="intensity (before)", color="tab:red")
    ax_vmr.bar(pos + 0.2, [c.vmr_reflectance for c in classes], width=0.4,
               label="reflectance (after)", color="tab:blue")
    ax_vmr.set_xticks(pos, labels)
    ax_vmr.set_ylabel("variance / mean (intensity units)", fontsize=_SMALL)
    ax_vmr.legend(fontsize=7)
    change = np.array([c.change * 100.0 for c in classes])
    colours = ["tab:green" if v < 0 else "tab:orange" for v in np.nan_to_num(change)]
    ax_change.bar(pos, np.nan_to_num(change), color=colours)
    ax_change.axhline(0.0, color="black", linewidth=0.8)
    ax_change.set_xticks(pos, labels)
    ax_change.set_ylabel("change of variance / mean (%)", fontsize=_SMALL)
    for axis in (ax_vmr, ax_change):
        axis.set_xlabel("terrain slope (deg)", fontsize=_SMALL)
        axis.tick_params(labelsize=7)
    return fig


def _robust_limits(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if not finite.size:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [2.0, 98.0])
    return float(lo), float(max(hi, lo + 1e-6))


def reflectance_figure(intensity: MapRaster, reflectance: MapRaster, unit: str,
                       crs: str) -> Figure:
    """Maps of the mean recorded intensity and the mean reflectance per cell (side by side,
    or one above the other for a mission much wider than high)."""
    ny, nx = reflectance.values.shape
    aspect = ny / max(nx, 1)
    if aspect < 0.6:
        fig = new_figure(12.0, float(np.clip(2 * 9.5 * aspect + 2.0, 4.0, 12.5)),
                         constrained=True)
        axes = fig.subplots(2, 1)
    else:
        fig = new_figure(12.0, float(np.clip(5.0 * aspect + 1.2, 3.0, 9.0)), constrained=True)
        axes = fig.subplots(1, 2)
    for ax, raster, label, bar in ((axes[0], intensity, "intensity (recorded)",
                                    "intensity units"),
                                   (axes[1], reflectance, "reflectance", unit)):
        vmin, vmax = _robust_limits(raster.values)
        image = _raster(ax, raster, cmap="gray", vmin=vmin, vmax=vmax)
        ax.set_title(f"{label}, {raster.cell_m:.1f} m cells", fontsize=9)
        _map_axes(ax, crs)
        colorbar = fig.colorbar(image, ax=ax, shrink=0.9)
        colorbar.set_label(bar, fontsize=_SMALL)
        colorbar.ax.tick_params(labelsize=7)
    return fig


__all__ = [
    "DIFFERENCE_CMAP", "FIGURE_DPI", "PAIR_POINTS_PER_CELL", "correlation_figure",
    "flight_map_figure", "new_figure", "pair_figure", "pair_limit_cm", "png_base64",
    "reflectance_figure", "swath_figure", "vmr_figure",
]
