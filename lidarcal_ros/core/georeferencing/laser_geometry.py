"""The laser geometry of each point: firing position, body frame and laser-frame coordinates.

``X = X_o + R rho``, ``rho = (x, y, z)`` in the body frame (right, forward, up), metres;
``R`` is ``R_kappa`` (level model, docs/method.md sections 2-4) or ``R_ins`` (section 10).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace

import numpy as np

from lidarcal_ros.core.georeferencing.heading import HeadingSource


class PositioningModel(enum.StrEnum):
    """The point-positioning model: the values of ``matching.model``
    (:mod:`lidarcal_ros.core.georeferencing.rigorous`), and ``LEVEL`` or ``RIGOROUS``, the
    model a strip got."""

    #: ``rigorous`` where the poses carry a usable attitude, else ``level``.
    AUTO = "auto"
    LEVEL = "level"
    RIGOROUS = "rigorous"


class ScannerKind(enum.StrEnum):
    """What the laser vector of a point may be (docs/method.md sections 10 and 12).

    ``LINEAR``: a line scanner's, ``rho = -r [sin beta, 0, cos beta]`` (its along-track part
    a small error); the bias columns of section 10 and the mirror scale ``dS``.
    ``GENERAL``: any direction (spinning multi-beam, Palmer, Livox; clouds in the sensor's
    frame): section 12's columns with ``y``, the range along ``rho``, no ``dS``.
    """

    LINEAR = "linear"
    GENERAL = "general"


@dataclass
class LaserGeometry:
    """Per-point quantities of docs/method.md sections 4 and 10 (all (n,) float64 unless stated).

    Attributes
    ----------
    x : lateral body-frame coordinate of the point seen from the firing position, metres,
        positive right of the flight direction.
    z : vertical body-frame coordinate, metres (negative: ground below the sensor).
    kappa : heading, radians, ``atan2(-d_x, d_y)`` of the body's forward axis ``d``.
    beta : mirror angle, radians, ``atan2(-x, -z)`` (``atan(x / z)`` for ``z < 0``).
    origin : (n, 3) firing position ``X_o(t)`` in the map frame, metres.
    rotation : (n, 3, 3) or None
        ``R_ins``, body (right, forward, up) to map, of each point (``rigorous``); None for
        ``level``, whose rotation is ``R_kappa``.
    y : (n,) or None
        Forward body-frame coordinate, metres (``rigorous``: a QA figure, about 0 for a
        linear scanner); None for ``level``.
    model : ``level`` or ``rigorous``.
    scanner : ScannerKind
        ``GENERAL`` (rigorous only): ``y`` is part of the laser vector and enters the bias
        columns and the correction; ``LINEAR``: it does not.
    timing : (n, 3) or None
        A ``GENERAL`` scanner's timing column (docs/method.md section 12: ``v + w x (X -
        X_o)``, map frame, m/s; the derivative of a point in its time): where given, the
        eighth bias (``dS``'s place; a general scanner has no ``dS``) is the timing bias
        ``dt`` (delivered - true time, s). None: no timing bias.
    """

    x: np.ndarray
    z: np.ndarray
    kappa: np.ndarray
    beta: np.ndarray
    origin: np.ndarray
    #: ``cos kappa``, ``sin kappa`` when known (one per trajectory window, spread to the
    #: points); else computed on first use by :meth:`trig`.
    cos_kappa: np.ndarray | None = None
    sin_kappa: np.ndarray | None = None
    #: ``sin beta``, ``cos beta`` when known; else computed on first use by :meth:`trig`.
    sin_beta: np.ndarray | None = None
    cos_beta: np.ndarray | None = None
    #: Where ``kappa`` came from: ``track`` or ``attitude``
    #: (:mod:`lidarcal_ros.core.georeferencing.heading`), and the median crab, deg (NaN: no attitude
    #: to compare the track with).
    heading_from: HeadingSource = HeadingSource.TRACK
    crab_deg: float = math.nan
    rotation: np.ndarray | None = None
    y: np.ndarray | None = None
    model: PositioningModel = PositioningModel.LEVEL
    scanner: ScannerKind = ScannerKind.LINEAR
    timing: np.ndarray | None = None

    @property
    def range(self) -> np.ndarray:
        """Range from the firing position, metres: ``sqrt(x^2 + z^2)`` (``level``),
        ``|rho|`` (``rigorous``)."""
        if self.y is None:
            return np.hypot(self.x, self.z)
        return np.sqrt(self.x * self.x + self.y * self.y + self.z * self.z)

    def trig(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``cos kappa, sin kappa, sin beta, cos beta`` per point.

        Float64 sine and cosine cost some 10 ns a point each, more than the rest of eq. [13]
        together, so the heading's come once per trajectory window and the mirror angle's
        from the coordinates: ``sin beta = -x / r``, ``cos beta = -z / r`` with ``r`` the
        :attr:`range` (docs/method.md section 10: ``sb = -x / r``, ``cb = -z / r``).
        """
        if not self.has_laser_frame:
            raise ValueError("the firing frames alone have no laser vectors: "
                             "corrected_geometry gives them")
        if self.cos_kappa is None or self.sin_kappa is None:
            self.cos_kappa = np.cos(self.kappa)
            self.sin_kappa = np.sin(self.kappa)
        if self.sin_beta is None or self.cos_beta is None:
            inv_r = 1.0 / self.range
            self.sin_beta, self.cos_beta = -self.x * inv_r, -self.z * inv_r
        return self.cos_kappa, self.sin_kappa, self.sin_beta, self.cos_beta

    def to_body(self, v: np.ndarray) -> np.ndarray:
        """Map-frame vectors (n, 3) in the body frame (right, forward, up): ``R^T v``."""
        if self.rotation is not None:
            return np.einsum("nji,nj->ni", self.rotation, v)
        c, s, _, _ = self.trig()
        out = np.empty_like(v, dtype=np.float64)
        out[:, 0] = c * v[:, 0] + s * v[:, 1]
        out[:, 1] = -s * v[:, 0] + c * v[:, 1]
        out[:, 2] = v[:, 2]
        return out

    def to_map(self, v: np.ndarray) -> np.ndarray:
        """Body-frame vectors (n, 3) in the map frame: ``R v``."""
        if self.rotation is not None:
            return np.einsum("nij,nj->ni", self.rotation, v)
        c, s, _, _ = self.trig()
        out = np.empty_like(v, dtype=np.float64)
        out[:, 0] = c * v[:, 0] - s * v[:, 1]
        out[:, 1] = s * v[:, 0] + c * v[:, 1]
        out[:, 2] = v[:, 2]
        return out

    @property
    def has_laser_frame(self) -> bool:
        """Whether it holds the laser vectors (``x``, ``z``, ``beta`` ...), not only the
        firing frames (:meth:`firing_frames`)."""
        return self.x.shape[0] == self.origin.shape[0]

    def firing_frames(self) -> LaserGeometry:
        """The firing positions and body frames alone (``origin``, heading or ``rotation``,
        ``timing``): what a correction starts from. The laser vectors (``x``, ``y``, ``z``,
        ``beta`` and its sine and cosine: 40-48 bytes a point) are left out, empty;
        :func:`~lidarcal_ros.core.georeferencing.bias_model.corrected_geometry` gives them
        where wanted."""
        c, s = self.cos_kappa, self.sin_kappa
        if c is None or s is None:
            c, s = np.cos(self.kappa), np.sin(self.kappa)
        empty = np.empty(0)
        return replace(self, x=empty, z=empty, beta=empty, cos_kappa=c, sin_kappa=s,
                       sin_beta=None, cos_beta=None, y=None)

    def take(self, index: np.ndarray) -> LaserGeometry:
        """A subset of the points (fancy or boolean index); the firing frames alone stay
        so."""
        def part(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[index]

        def vector(a: np.ndarray) -> np.ndarray:
            return a[index] if self.has_laser_frame else a

        return LaserGeometry(
            vector(self.x), vector(self.z), self.kappa[index], vector(self.beta),
            self.origin[index],
            cos_kappa=part(self.cos_kappa), sin_kappa=part(self.sin_kappa),
            sin_beta=part(self.sin_beta), cos_beta=part(self.cos_beta),
            heading_from=self.heading_from, crab_deg=self.crab_deg,
            rotation=part(self.rotation), y=part(self.y), model=self.model,
            scanner=self.scanner, timing=part(self.timing),
        )

    @classmethod
    def empty(cls, model: PositioningModel = PositioningModel.LEVEL,
              scanner: ScannerKind = ScannerKind.LINEAR) -> LaserGeometry:
        """No points."""
        e = np.empty(0)
        rigorous = model == PositioningModel.RIGOROUS
        return cls(e, e, e, e, np.empty((0, 3)), model=model,
                   rotation=np.empty((0, 3, 3)) if rigorous else None,
                   y=e if rigorous else None, scanner=scanner)

    @property
    def general_y(self) -> np.ndarray:
        """``y`` where it enters the bias columns (a ``GENERAL`` scanner's), else an empty
        array (the compiled loops' way of saying "0 for every point")."""
        if self.scanner is ScannerKind.GENERAL and self.y is not None:
            return self.y
        return _NO_Y


def geometry_at(xyz: np.ndarray, frame: LaserGeometry) -> LaserGeometry:
    """The laser geometry of points ``xyz`` (n, 3, map frame, m) seen from the firing
    positions and body frames of ``frame`` (one per point): where a point moved by the
    correction is seen from.

    The level model's ``x`` is the horizontal distance across the heading and ``z`` the
    height difference (docs/method.md section 4); the rigorous model's ``(x, y, z)`` is
    ``R_ins^T (X - X_o)`` (section 10).
    """
    rel = xyz - frame.origin
    c, s = frame.cos_kappa, frame.sin_kappa
    if c is None or s is None:
        c, s, _, _ = frame.trig()
    if frame.rotation is not None:
        rho = np.einsum("nji,nj->ni", frame.rotation, rel)
        x, y, z = rho[:, 0], rho[:, 1], rho[:, 2]
    else:
        x, y, z = rel[:, 0] * c + rel[:, 1] * s, None, rel[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.arctan(x / z)
    return LaserGeometry(x=x, z=z, kappa=frame.kappa, beta=beta, origin=frame.origin,
                         cos_kappa=c, sin_kappa=s, heading_from=frame.heading_from,
                         crab_deg=frame.crab_deg, rotation=frame.rotation, y=y,
                         model=frame.model, scanner=frame.scanner, timing=frame.timing)


_NO_Y = np.zeros(0)

__all__ = ["LaserGeometry", "PositioningModel", "ScannerKind", "geometry_at"]
