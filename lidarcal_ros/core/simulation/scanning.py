"""The simulated scanner: one line's pulses, what the biased system reports, and the intensity.

A linear scanner at a constant pulse rate; the exact bias model of :mod:`.exact_model`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.simulation.exact_model import georeference
from lidarcal_ros.core.simulation.flight_path import FlightLine
from lidarcal_ros.core.simulation.ray_casting import cast_rays
from lidarcal_ros.core.simulation.surface import Surface

WAVELENGTH_NM = 1064.0
#: Radiometric constant: I = K rho cos(inc) exp(-2 alpha r) / r^2. About 3800 for a 0.5
#: reflectance at normal incidence from 1150 m, about 17000 from 540 m: fits uint16.
INTENSITY_K = 1.0e10
#: Pulses cast at a time (bounds memory).
PULSE_BLOCK = 262_144


def swath_width(height: float, fov_deg: float) -> float:
    """Swath width on flat ground at ``height`` metres below the sensor."""
    return 2.0 * height * math.tan(math.radians(fov_deg) / 2.0)


def pulse_and_scan_rates(
    density: float, speed_mps: float, fov_deg: float, height: float
) -> tuple[float, float]:
    """PRF (Hz) and mirror frequency (full zig-zag periods per second) for a mean point density.

    ``density`` is the mean over the swath at ``height`` on flat ground:
    ``PRF = density * speed * swath``; the mirror frequency ``speed * sqrt(density) / 2`` makes
    the mean along-track spacing of sweeps equal to the mean across-track spacing of points.
    """
    prf = density * speed_mps * swath_width(height, fov_deg)
    scan = speed_mps * math.sqrt(density) / 2.0
    return prf, scan


def triangle(phase: np.ndarray) -> np.ndarray:
    """Triangle wave of period 1 in [-1, 1], -1 at phase 0."""
    frac = np.mod(phase, 1.0)
    return 1.0 - 4.0 * np.abs(frac - 0.5)


@dataclass(frozen=True)
class Scanner:
    """The scanner of a mission, the air it fires through and its noise.

    Attributes
    ----------
    prf_hz : float
        Pulses per second.
    scan_rate_hz : float
        Full zig-zag periods of the mirror per second.
    half_fov_rad : float
        Half the field of view, rad: the mirror angle sweeps ``[-half_fov_rad, half_fov_rad]``.
    biases : dict
        Bias values (nominal - true), SI, of :data:`~lidarcal_ros.core.params.PARAMETER_NAMES`.
    atmospheric_alpha_per_m : float
        Extinction coefficient of the air, per metre.
    range_noise_m : float
        Gaussian range noise, metres.
    intensity_noise : float
        Relative (multiplicative) Gaussian noise of the intensities.
    """

    prf_hz: float
    scan_rate_hz: float
    half_fov_rad: float
    biases: dict[str, float]
    atmospheric_alpha_per_m: float
    range_noise_m: float
    intensity_noise: float


@dataclass
class LineScan:
    """One line's pulses: what the biased system delivers and the truth (local coordinates
    until the mission moves them to the map's).

    Attributes
    ----------
    xyz_b : (n, 3) float64
        Points the biased system reports.
    xyz_t : (n, 3) float64
        True points.
    cls : (n,) int8
        Surface class hit (:mod:`lidarcal_ros.core.simulation.surface`).
    incidence : (n,) float32
        True incidence angle, rad.
    reflectance : (n,) float32
        True reflectance.
    range_true : (n,) float64
        True range, metres.
    theta : (n,) float32
        Physical mirror angle, rad.
    on_wall : (n,) bool
        The pulse stopped on a wall.
    intensity : (n,) float32
        Recorded intensity.
    """

    xyz_b: np.ndarray
    xyz_t: np.ndarray
    cls: np.ndarray
    incidence: np.ndarray
    reflectance: np.ndarray
    range_true: np.ndarray
    theta: np.ndarray
    on_wall: np.ndarray
    intensity: np.ndarray

    @classmethod
    def empty(cls, n: int) -> LineScan:
        """A scan of ``n`` pulses, its arrays allocated and not filled."""
        return cls(np.empty((n, 3)), np.empty((n, 3)), np.empty(n, dtype=np.int8),
                   np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32), np.empty(n),
                   np.empty(n, dtype=np.float32), np.empty(n, dtype=bool),
                   np.empty(n, dtype=np.float32))


def scan_line(flight: FlightLine, n: int, surface: Surface, scanner: Scanner,
              rng: np.random.Generator) -> LineScan:
    """Fire the line's ``n`` pulses (docs/internals.md), the first at the line's start; the
    range and intensity noise from ``rng``, block by block. Local coordinates."""
    out = LineScan.empty(n)
    for i0, block in scan_blocks(flight, n, surface, scanner, rng):
        sl = slice(i0, i0 + len(block.xyz_b))
        for name in LineScan.__dataclass_fields__:
            getattr(out, name)[sl] = getattr(block, name)
    return out


def scan_blocks(flight: FlightLine, n: int, surface: Surface, scanner: Scanner,
                rng: np.random.Generator) -> Iterator[tuple[int, LineScan]]:
    """:func:`scan_line` one block of :data:`PULSE_BLOCK` pulses at a time: ``(i0, scan)``,
    the block's first pulse index and its pulses (the same values, drawn in the same order),
    so a line of any length is fired in bounded memory."""
    for i0 in range(0, n, PULSE_BLOCK):
        yield i0, _scan_block(flight, i0, min(i0 + PULSE_BLOCK, n), surface, scanner, rng)


def skip_noise(n: int, scanner: Scanner, rng: np.random.Generator) -> None:
    """Draw from ``rng`` what firing ``n`` pulses draws (:func:`scan_blocks`), and nothing else:
    ``rng`` left where a scan of the line would leave it."""
    for i0 in range(0, n, PULSE_BLOCK):
        _draw_noise(min(i0 + PULSE_BLOCK, n) - i0, scanner, rng)


def _draw_noise(m: int, scanner: Scanner, rng: np.random.Generator
                ) -> tuple[np.ndarray | float, np.ndarray | None]:
    """A block's range noise (m) and relative intensity noise, in the order they are drawn."""
    noise = rng.normal(0.0, scanner.range_noise_m, m) if scanner.range_noise_m > 0 else 0.0
    inoise = rng.standard_normal(m) if scanner.intensity_noise > 0 else None
    return noise, inoise


def _scan_block(flight: FlightLine, i0: int, i1: int, surface: Surface, scanner: Scanner,
                rng: np.random.Generator) -> LineScan:
    """Pulses ``i0`` to ``i1`` (excluded) of the line."""
    trel = np.arange(i0, i1, dtype=np.float64) / scanner.prf_hz
    theta = scanner.half_fov_rad * triangle(trel * scanner.scan_rate_hz)
    m = i1 - i0
    state = flight.state(trel)
    r_ins = state.rotation()
    st, ct = np.sin(theta), np.cos(theta)
    d = np.empty((m, 3))
    for j in range(3):  # R_ins times the body's beam (-sin theta, 0, -cos theta)
        d[:, j] = r_ins[:, j, 0] * -st + r_ins[:, j, 2] * -ct
    hits = cast_rays(surface, state.position, d)
    noise, inoise = _draw_noise(m, scanner, rng)
    xb = georeference(state.position, r_ins, hits.t, theta, scanner.biases, noise)
    # The class from just inside what was hit (a wall's object, not the ground before it);
    # a wall's normal is horizontal, the height field's is not.
    cl, rho = surface.class_and_reflectance_local(hits.inside[:, 0], hits.inside[:, 1])
    nrm = surface.normal_local(hits.xyz[:, 0], hits.xyz[:, 1])
    if hits.on_wall.any():
        w = hits.on_wall
        nrm[w] = surface.wall_normal_local(hits.inside[w, 0], hits.inside[w, 1])
    cos_inc = np.clip(np.abs(np.einsum("ij,ij->i", nrm, d)), 0.0, 1.0)
    amp = (INTENSITY_K * rho * cos_inc * np.exp(-2.0 * scanner.atmospheric_alpha_per_m
                                                * hits.t) / hits.t**2)
    if inoise is not None:
        amp *= 1.0 + scanner.intensity_noise * inoise
    out = LineScan.empty(m)
    out.xyz_b[:] = xb
    out.xyz_t[:] = hits.xyz
    out.cls[:] = cl
    out.incidence[:] = np.arccos(cos_inc)
    out.reflectance[:] = rho
    out.range_true[:] = hits.t
    out.theta[:] = theta
    out.on_wall[:] = hits.on_wall
    out.intensity[:] = np.maximum(amp, 0.0)
    return out


__all__ = ["INTENSITY_K", "PULSE_BLOCK", "WAVELENGTH_NM", "LineScan", "Scanner",
           "pulse_and_scan_rates", "scan_blocks", "scan_line", "skip_noise", "swath_width",
           "triangle"]
