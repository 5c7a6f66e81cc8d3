"""The sections of the HTML report, one function each, in the order of the page."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.calibration.result import ControlResidual
from lidarcal_ros.core.params import display_value
from lidarcal_ros.core.qa.accuracy import RIGID_NAMES, RigidFit
from lidarcal_ros.core.qa.quality_level import LBS_LEVELS
from lidarcal_ros.core.qa.swath_differences import DzStatistics
from lidarcal_ros.core.units import format_cm, format_number
from lidarcal_ros.io.report import figures
from lidarcal_ros.io.report.content import BiasEntry, EvaluationSection, Provenance, ReportContent
from lidarcal_ros.io.report.elements import (
    FigureRenderer,
    escape,
    facts_table,
    html_section,
    html_table,
    note,
)

__all__ = [
    "block_html", "calibration_html", "control_html", "evaluation_html", "pairs_html",
    "provenance_html", "quality_html", "radiometry_html", "summary_html", "swath_html",
    "trajectory_html",
]


def summary_html(content: ReportContent) -> str:
    """The summary: the quality-level statement, the mission's facts, the warnings."""
    parts = []
    if content.quality is not None:
        parts.append(f'<p class="statement" id="ql-statement">'
                     f"{escape(content.quality.statement())}</p>")
    parts.append(facts_table(content.facts))
    parts.extend(f'<p class="WARN">warning: {escape(w)}</p>' for w in content.warnings)
    return html_section("summary", "Summary", parts)


def quality_html(content: ReportContent) -> str:
    """Each USGS LBS measure against the thresholds of QL0-QL3, and the level met."""
    quality = content.quality
    if quality is None:
        return html_section("quality", "Quality level (USGS Lidar Base Specification)",
                            ["<p>Not assessed: no swath differences.</p>"])
    header = ["measure", "measured", *(level.name for level in LBS_LEVELS), "how"]
    rows = []
    for c in quality.criteria:
        density = c.at_least
        value = (f"{c.value:.2f} /m&sup2;" if density else f"{format_cm(c.value)} cm") \
            if c.assessed else "not assessed"
        cells = [escape(c.name), value]
        for level in LBS_LEVELS:
            limit = c.threshold(level)
            shown = f"&ge; {limit:g} /m&sup2;" if density else f"&le; {limit * 100:g} cm"
            met = c.met(level)
            mark = "" if met is None else (' <span class="met">met</span>' if met
                                           else ' <span class="missed">missed</span>')
            cells.append(shown + mark)
        cells.append(escape(c.note))
        rows.append(cells)
    best = quality.best
    verdict = ["<tr><td><b>quality level</b></td><td></td>"]
    for level in LBS_LEVELS:
        ok = quality.met(level)
        verdict.append(f'<td><span class="{"met" if ok else "missed"}">'
                       f'{"met" if ok else "not met"}</span></td>')
    verdict.append(f"<td>best: {best.name if best else 'none'}</td></tr>")
    table = html_table(header, rows, {1}).replace("</tbody>", "".join(verdict) + "</tbody>")
    return html_section("quality", "Quality level (USGS Lidar Base Specification)", [
        f'<p class="statement">{escape(quality.statement())}</p>', table,
        note("Interswath measures: the height differences between overlapping strips after "
             "calibration, over smooth level ground (see Swath differences). A level is met "
             "when every assessed measure is within its threshold; QL1 and QL2 differ only "
             "in density. The pair QA of this report (OK/WARN/ERROR) uses the "
             f"configuration's qa.rmsdz_warn_m ({content.qa_warn_m * 100:g} cm) and "
             f"qa.max_difference_m ({content.qa_error_m * 100:g} cm). Intraswath "
             "smooth-surface precision is not assessed.")])


def block_html(content: ReportContent, draw: FigureRenderer) -> str:
    """The block map (flight lines, trajectory, control and check points) and the strip table."""
    parts = []
    crs = content.crs or "map frame (CRS not given: lidarcal report --crs names it)"
    if content.flight is not None:
        parts.append(draw.figure(
            "fig-flight-map", "flight lines, trajectory, control and check points",
            figures.flight_map_figure(content.flight, content.crs),
            f"Flight lines (the trajectory while each strip was flown, arrow: direction, "
            f"number: strip id) over the cells the strips cover; grey: the rest of the "
            f"trajectory. Coordinates: {escape(crs)}."))
    if content.strips:
        rows = [[str(s.strip_id), str(s.points), escape(s.start), f"{s.duration_s:.1f}",
                 f"{s.length_m:.0f}", f"{s.heading_deg:.1f}", f"{s.speed_mps:.1f}",
                 f"{s.height_m:.0f}", f"{s.density_per_m2:.2f}"] for s in content.strips]
        parts.append(html_table(["strip", "points", "first point", "duration (s)", "length (m)",
                                 "heading (deg)", "speed (m/s)", "height above ground (m)",
                                 "density (/m&sup2;)"], rows, {1, 3, 4, 5, 6, 7, 8}))
        parts.append(note("Heading: course over ground, degrees clockwise from grid north. "
                          "Height above ground: median trajectory height minus median "
                          "point height. Density: points over the area of the cells "
                          "holding the strip's points."))
    return html_section("block", "Block: flight lines and strips", parts)


def _bias_display(name: str, value: float) -> tuple[str, str]:
    """Value and unit as read by people (arcsec, cm, or a plain scale factor)."""
    shown, unit = display_value(name, value)
    return (f"{shown:+.3e}", "1") if name == "dS" else (f"{shown:+.2f}", unit)


def _bias_rows(biases: Sequence[BiasEntry]) -> list[list[str]]:
    rows = []
    for b in biases:
        value, unit = _bias_display(b.name, b.value)
        sigma = _bias_display(b.name, b.sigma)[0].lstrip("+") if b.sigma is not None else ""
        state = {ParameterState.ESTIMATED: "estimated",
                 ParameterState.FIXED: "fixed (not solved for)"}.get(b.state, "not estimable")
        if b.reason:
            state += f": {escape(b.reason)}"
        rows.append([escape(b.name), value, sigma, unit, state])
    return rows


def calibration_html(content: ReportContent, draw: FigureRenderer) -> str:
    """The calibration's facts, the bias table and the correlation matrix."""
    parts = [facts_table(content.calibration_facts),
             html_table(["parameter", "estimate", "sigma", "unit", "status"],
                        _bias_rows(content.biases), {1, 2}),
             note("A bias is the nominal value used by the system minus the true one; lever "
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
    return html_section("calibration", "Calibration", parts)


def _with_sigma(values: np.ndarray, sigmas: np.ndarray | None, scale: float, digits: int
                ) -> list[str]:
    """``value &plusmn; sigma`` per axis, scaled (cm, mm/s), sigma left out where unknown."""
    out = []
    for k in range(3):
        text = f"{values[k] * scale:+.{digits}f}"
        if sigmas is not None and math.isfinite(float(sigmas[k])):
            text += f" &plusmn; {sigmas[k] * scale:.{digits}f}"
        out.append(text)
    return out


def trajectory_html(content: ReportContent, draw: FigureRenderer) -> str:
    """Each strip's estimated trajectory error: the model, its curves over time with their
    sigma band, and per strip offset and drift with their sigmas ('' without the block)."""
    section = content.trajectory
    if section is None:
        return ""
    estimate = section.estimate
    drift = estimate.model.value == "drift"
    parts = [facts_table([("trajectory model", escape(section.choice)),
                          ("strips", str(len(estimate.strips)))]),
             draw.figure("fig-trajectory-errors",
                         "each strip's estimated trajectory error over time, E, N, U",
                         figures.trajectory_figure(section),
                         "Each strip's estimated trajectory error e_s(t) (delivered - true, "
                         "map frame: E = x, N = y, U = z; cm) over the time its points were "
                         "flown (number: strip id), shaded: one sigma, sqrt(offset_sigma^2 + "
                         "(t - t_ref)^2 drift_sigma^2) per axis, the covariance of offset and "
                         "drift left out (the file does not hold it).")]
    rows = []
    for sid in sorted(estimate.strips):
        se = estimate.strips[sid]
        lo, hi = section.spans.get(sid, (math.nan, math.nan))
        flown = (f"{lo - section.t0:.1f} - {hi - section.t0:.1f}" if math.isfinite(lo)
                 else "not in the bag")
        row = [str(sid), flown, f"{se.t_ref - section.t0:.1f}",
               *_with_sigma(se.offset, se.offset_sigma, 100.0, 1)]
        if drift and se.drift is not None:
            row += _with_sigma(se.drift, se.drift_sigma, 1000.0, 2)
        rows.append(row)
    header = ["strip", "flown (s)", "t_ref (s)", "offset E (cm)", "offset N (cm)",
              "offset U (cm)"]
    if drift:
        header += ["drift E (mm/s)", "drift N (mm/s)", "drift U (mm/s)"]
    parts.append(html_table(header, rows, set(range(1, len(header)))))
    parts.append(note(
        f"Times in seconds since {escape(section.start)}; t_ref is the strip's reference time "
        "(its mid time), about which the drift runs. lidarcal correct removes e_s(t) from each "
        "point of strip s and, on --trajectory-out and /lidar/trajectory_corrected, from the "
        "trajectory. The horizontal offsets also take what the data cannot tell them from: "
        "the lever arm, and boresight angles held at their values (docs/method.md section 11); "
        "their sigmas do not include a bias held wrong."))
    return html_section("trajectory", "Trajectory errors: each strip's correction", parts)


def swath_html(content: ReportContent, draw: FigureRenderer) -> str:
    """The swath-to-swath height differences before and after: mosaics and per-pair table."""
    swath = content.swath
    title = "Swath differences: strip-to-strip heights over the block"
    if swath is None or not swath.pairs:
        return html_section("swath", title, ["<p>No two strips share smooth ground.</p>"])
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
    parts.append(html_table(["strips", "dz", "cells", "RMSDz before (cm)", "RMSDz after (cm)",
                             "max |dz| before (cm)", "max |dz| after (cm)"], rows,
                            {2, 3, 4, 5, 6}))
    parts.append(note(
        "Each strip's height per cell is the mean of its points there, each carried to the "
        "cell centre along its own surface normal. Smooth ground only: the strip has at least "
        "two points in the cell, every one with a trusted normal (no vegetation, edge or "
        f"wall) on a slope below {content.smooth_slope_deg:g} deg and at one height, and so "
        "do the neighbouring cells, without a step between them; elsewhere the cells are "
        "blank and not counted (pitched roofs, the surroundings of buildings, trees). "
        f"Coordinates: {escape(content.crs or 'map frame')}."))
    return html_section("swath", title, parts)


def pairs_html(content: ReportContent, draw: FigureRenderer) -> str:
    """Per strip pair the normal discrepancies of the calibration's sample points."""
    title = "Strip pairs: normal discrepancies of the calibration's sample points"
    if not content.pairs:
        return html_section("pairs", title, ["<p>No overlapping strip pairs.</p>"])
    rows = []
    for p in content.pairs:
        a, b = p.strips
        coverage = f"{p.coverage * 100:.0f}%" if p.coverage is not None else ""
        rows.append([f'<a href="#pair-{a}-{b}">{a} &amp; {b}</a>', coverage,
                     str(p.after.distance.size), format_cm(p.before.rms), format_cm(p.after.rms),
                     format_cm(p.after.p95), f'<span class="{p.qa_level}">{p.qa_level}</span>'])
    parts = [html_table(["strips", "coverage", "points", "RMS before (cm)", "RMS after (cm)",
                         "95% after (cm)", "QA"], rows, {1, 2, 3, 4, 5}),
             note("Signed distance of each sample point of the calibration from the other "
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
    return html_section("pairs", title, parts)


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


def evaluation_html(section: EvaluationSection | None) -> str:
    """``lidarcal evaluate``'s co-alignment of each pair and check-point residuals."""
    title = "Accuracy: co-alignment of strip pairs and check points (lidarcal evaluate)"
    if section is None:
        return html_section("evaluation", title, ["<p>Not evaluated.</p>"])
    parts = [f"<p>{escape(section.source)}</p>", "<h3>Relative accuracy: rigid transformation "
             "co-aligning each strip pair (point-to-patch ICP)</h3>"]
    if section.pairs:
        rows = []
        for a, b, before, after in section.pairs:
            rows.append([f"{a} &amp; {b}", "before", *_fit_cells(before)])
            rows.append(["", "after", *_fit_cells(after)])
        parts.append(html_table(["strips", "state", "tx (cm)", "ty (cm)", "tz (cm)",
                                 "omega (\")", "phi (\")", "kappa (\")", "RMS cm (fitted)",
                                 "matches"], rows, set(range(2, 10))))
        parts.append(note("The transformation moving the first strip's points onto the "
                          "second strip's TIN: near zero after a good calibration. '-': not "
                          "determined by the overlap's shape (flat ground hides horizontal "
                          "shifts and the rotation about the vertical)."))
    else:
        parts.append("<p>No overlapping strip pairs.</p>")
    parts.append("<h3>Absolute accuracy: check points (strip surface minus surveyed "
                 "height)</h3>")
    if section.check:
        rows = [[escape(pid), escape(",".join(map(str, strips)) or "-"), format_cm(b, sign=True),
                 format_cm(a, sign=True)] for pid, strips, b, a in section.check]
        parts.append(html_table(["check point", "strips", "before (cm)", "after (cm)"], rows,
                                {2, 3}))
        rows = []
        for state in ("before", "after"):
            s = section.summary(state)
            rows.append([state, str(s.n), format_cm(s.mean, sign=True), format_cm(s.std),
                         format_cm(s.rmse), format_cm(s.max_abs)])
        parts.append(html_table(["state", "n", "mean (cm)", "std (cm)", "RMSE (cm)",
                                 "max |r| (cm)"], rows, {1, 2, 3, 4, 5}))
    else:
        parts.append("<p>No check points (lidarcal report --check-points CSV).</p>")
    return html_section("evaluation", title, parts)


def control_html(control: Sequence[ControlResidual]) -> str:
    """The residuals of the control points used by the calibration."""
    title = "Control points used by the calibration"
    if not control:
        return html_section("control", title, ["<p>No control point falls on a strip.</p>"])
    rows = [[escape(c.control_id), str(c.strip_id), format_cm(c.before, sign=True),
             format_cm(c.after, sign=True)] for c in control]
    return html_section("control", title, [
        html_table(["control point", "strip", "before (cm)", "after (cm)"], rows, {1, 2, 3}),
        note("Signed normal distance of the control point from the strip's TIN patch, "
             "control minus strip; n/a: no patch within the threshold after correction.")])


def radiometry_html(content: ReportContent, draw: FigureRenderer) -> str:
    """The reflectance's meaning, its variance-to-mean ratio per slope class, the maps."""
    section = content.radiometry
    title = "Radiometric correction"
    if section is None:
        return html_section("radiometry", title,
                            ["<p>The clouds carry no intensity: no radiometric correction.</p>"])
    unit = "" if section.unit == "1" else " (intensity units)"
    rows = [[f"{c.lo_deg:.0f}-{c.hi_deg:.0f}", str(c.n_points), format_number(c.mean_intensity),
             format_number(c.vmr_intensity), format_number(c.mean_reflectance),
             format_number(c.vmr_reflectance),
             "n/a" if not math.isfinite(c.change) else f"{c.change * 100:+.1f}%"]
            for c in section.slope_classes]
    parts = [f'<p id="reflectance-meaning"><b>Reflectance</b>: {escape(section.meaning)}</p>',
             html_table(["slope (deg)", "points", "mean intensity", "VMR intensity",
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
    parts.append("".join(note(escape(n)) for n in notes))
    return html_section("radiometry", title, parts)


def _file_size_text(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} B" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024  # type: ignore[assignment]
    return f"{n} B"  # pragma: no cover


def provenance_html(provenance: Provenance | None) -> str:
    """The lidarcal version, the date, the command, the inputs and the configuration."""
    if provenance is None:
        return html_section("provenance", "Provenance", ["<p>Not recorded.</p>"])
    facts = [("lidarcal", provenance.version), ("generated (UTC)", provenance.generated)]
    if provenance.command:
        facts.append(("command", provenance.command))
    facts.append(("flight configuration", provenance.configuration_source))
    rows = [[escape(f.role), escape(f.path), _file_size_text(f.size_bytes), f'<span class="mono">'
             f"{escape(f.sha256)}</span>"] for f in provenance.inputs]
    changed = [(n, v) for n, v, c in provenance.configuration if c]
    config_rows = [[escape(n), escape(v)] for n, v, _ in provenance.configuration]
    classes = ["changed" if c else "" for _, _, c in provenance.configuration]
    return html_section("provenance", "Provenance", [
        facts_table(facts),
        "<h3>Inputs</h3>",
        html_table(["input", "path", "size", "SHA-256"], rows, {2}),
        note("The SHA-256 of a directory (a rosbag2 bag) is that of its files' names and "
             "contents in name order."),
        "<h3>Flight configuration</h3>",
        (f"<p>Differs from the defaults in: {escape(', '.join(f'{n} = {v}' for n, v in changed))}"
         "</p>" if changed else "<p>All parameters at their defaults.</p>"),
        "<details><summary>every parameter</summary>"
        + html_table(["parameter", "value"], config_rows, set(), row_classes=classes)
        + "</details>"])
