"""The surface a simulated mission scans: its classes, and what the simulator asks of it.

Map-frame methods take map coordinates, ``*_local`` ones map minus ``origin``. Classes: 0
ground-soil, 1 grass, 2 asphalt, 3 roof, 4 tree crown.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from lidarcal_ros.core.simulation.object_tops import ObjectTops

#: Surface class codes.
SOIL, GRASS, ASPHALT, ROOF, TREE = 0, 1, 2, 3, 4
CLASS_NAMES: dict[int, str] = {
    SOIL: "ground-soil", GRASS: "grass", ASPHALT: "asphalt", ROOF: "roof", TREE: "tree",
}
#: Nominal Lambertian reflectance of each class at 1064 nm (each object varies by +-10%).
CLASS_REFLECTANCE: dict[int, float] = {
    SOIL: 0.30, GRASS: 0.45, ASPHALT: 0.12, ROOF: 0.25, TREE: 0.50,
}


class Surface(ABC):
    """A surface to scan (module docstring): local-frame queries for the simulator and the
    ray caster, map-frame ones for everyone else.

    Attributes
    ----------
    origin : (x0, y0)
        Added to local coordinates to give map coordinates, metres.
    extent : (xmin, xmax, ymin, ymax)
        Where the surface's features lie, local coordinates, metres.
    kind : str
        ``"built-up"``, ``"flat"`` or ``"dsm"``.
    object_tops : ObjectTops or None
        Where objects (buildings, trees) may stop a ray before the ground; None where the
        height field is the ground alone.
    """

    origin: tuple[float, float]
    extent: tuple[float, float, float, float]
    kind: str
    object_tops: ObjectTops | None

    # ------------------------------------------------------------------ local frame

    @abstractmethod
    def height_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface height (ground, roofs, crowns) at local (x, y) (n,), metres."""

    @abstractmethod
    def ground_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bare-ground height (objects ignored) at local (x, y) (n,), metres."""

    @abstractmethod
    def class_and_reflectance_local(self, x: np.ndarray, y: np.ndarray
                                    ) -> tuple[np.ndarray, np.ndarray]:
        """Class code (int8) and Lambertian reflectance (float64) at local (x, y) (n,)."""

    @abstractmethod
    def normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Upward unit normal (n, 3) of the height field at local (x, y) (n,)."""

    @abstractmethod
    def wall_normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Horizontal outward normal (n, 3) of the nearest wall of the object at local
        (x, y) (n,); (0, 0, 1) where there is no object."""

    @abstractmethod
    def ground_hit(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance (n,) along each downward unit ray (origins and directions (n, 3), local)
        to the ground, objects ignored, metres."""

    # ------------------------------------------------------------------ the whole surface

    @abstractmethod
    def describe(self) -> dict[str, object]:
        """Summary for a truth file."""

    @property
    @abstractmethod
    def n_buildings(self) -> int:
        """How many buildings stand on the surface."""

    @property
    @abstractmethod
    def n_trees(self) -> int:
        """How many trees stand on the surface."""

    # ------------------------------------------------------------------ map frame

    def _to_local(self, x: np.ndarray | float, y: np.ndarray | float
                  ) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
        xa = np.asarray(x, dtype=np.float64) - self.origin[0]
        ya = np.asarray(y, dtype=np.float64) - self.origin[1]
        xa, ya = np.broadcast_arrays(xa, ya)
        return xa.ravel(), ya.ravel(), xa.shape

    def height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Surface height (DSM: ground, roofs, crowns) at map coordinates, metres."""
        xl, yl, shape = self._to_local(x, y)
        return self.height_local(xl, yl).reshape(shape)

    def ground_height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Bare-ground height (ignores buildings and trees), metres."""
        xl, yl, shape = self._to_local(x, y)
        return self.ground_local(xl, yl).reshape(shape)

    def surface_class(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Surface class codes (int8): 0 soil, 1 grass, 2 asphalt, 3 roof, 4 tree crown."""
        xl, yl, shape = self._to_local(x, y)
        return self.class_and_reflectance_local(xl, yl)[0].reshape(shape)

    def reflectance(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """True Lambertian reflectance of the surface (class value, +-10% per object/patch)."""
        xl, yl, shape = self._to_local(x, y)
        return self.class_and_reflectance_local(xl, yl)[1].reshape(shape)

    def normal(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Upward unit normal of the surface, shape ``(*shape, 3)``.

        Walls are not part of the height field: see :meth:`wall_normal`.
        """
        xl, yl, shape = self._to_local(x, y)
        return self.normal_local(xl, yl).reshape(*shape, 3)

    def wall_normal(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Horizontal outward normal of the nearest wall of the object at (x, y)."""
        xl, yl, shape = self._to_local(x, y)
        return self.wall_normal_local(xl, yl).reshape(*shape, 3)


__all__ = ["ASPHALT", "CLASS_NAMES", "CLASS_REFLECTANCE", "GRASS", "ROOF", "SOIL", "TREE",
           "Surface"]
