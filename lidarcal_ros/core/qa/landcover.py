"""Land-cover classification from LiDAR rasters (the paper's Tables 6 and 7).

Rasters, classifier and accuracy: docs/internals.md, "Quality measures".
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import grey_opening

logger = logging.getLogger(__name__)


@dataclass
class Raster:
    """Features of the occupied cells of a grid.

    Attributes
    ----------
    cell_m : float
        Cell size, metres.
    origin : (float, float)
        Map coordinates of the grid's lower-left corner, metres.
    shape : (int, int)
        Rows (y) and columns (x) of the grid.
    index : (m,) int64
        Flat index ``row * columns + column`` of each occupied cell.
    """

    cell_m: float
    origin: tuple[float, float]
    shape: tuple[int, int]
    index: np.ndarray

    @classmethod
    def covering(cls, xy: np.ndarray, cell_m: float) -> tuple[Raster, np.ndarray]:
        """The grid over ``xy`` (map frame, m) and the flat cell index of every point."""
        if not cell_m > 0:
            raise ValueError(f"cell size must be positive, got {cell_m}")
        x0, y0 = float(np.min(xy[:, 0])), float(np.min(xy[:, 1]))
        col = ((xy[:, 0] - x0) / cell_m).astype(np.int64)
        row = ((xy[:, 1] - y0) / cell_m).astype(np.int64)
        shape = (int(row.max()) + 1, int(col.max()) + 1)
        flat = row * shape[1] + col
        return cls(cell_m, (x0, y0), shape, np.unique(flat)), flat

    def mean(self, flat: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Mean of ``values`` per occupied cell (NaN values ignored; NaN if none)."""
        ok = np.isfinite(values)
        size = self.shape[0] * self.shape[1]
        total = np.bincount(flat[ok], weights=values[ok], minlength=size)
        count = np.bincount(flat[ok], minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            return (total / count)[self.index]

    def majority(self, flat: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
        """Most frequent label per occupied cell."""
        size = self.shape[0] * self.shape[1]
        counts = np.zeros((n_labels, self.index.size))
        for k in range(n_labels):
            counts[k] = np.bincount(flat[labels == k], minlength=size)[self.index]
        return np.argmax(counts, axis=0)

    def normalised_dsm(self, flat: np.ndarray, z: np.ndarray, ground_window_m: float
                       ) -> np.ndarray:
        """Highest point per occupied cell minus the ground (docs/internals.md), metres."""
        size = self.shape[0] * self.shape[1]
        top = np.full(size, -np.inf)
        np.maximum.at(top, flat, z)
        grid = top.reshape(self.shape)
        # Empty cells must not become ground: give them the highest value.
        filled = np.where(np.isfinite(grid), grid, np.max(top[self.index]))
        width = max(3, int(math.ceil(ground_window_m / self.cell_m)) | 1)
        ground = grey_opening(filled, size=(width, width), mode="nearest")
        return (grid - ground).reshape(-1)[self.index]


@dataclass
class GaussianML:
    """Gaussian maximum-likelihood classifier (docs/internals.md, "Quality measures").

    Attributes
    ----------
    means : (c, k) float64
    covariances : (c, k, k) float64
    """

    means: np.ndarray
    covariances: np.ndarray

    @classmethod
    def fit(cls, features: np.ndarray, labels: np.ndarray, n_classes: int) -> GaussianML:
        """Class statistics from training samples.

        Raises
        ------
        ValueError
            A class has fewer training samples than features + 1.
        """
        k = features.shape[1]
        means = np.zeros((n_classes, k))
        covs = np.zeros((n_classes, k, k))
        for c in range(n_classes):
            x = features[labels == c]
            if x.shape[0] <= k:
                raise ValueError(f"class {c}: {x.shape[0]} training samples, need > {k}")
            means[c] = x.mean(axis=0)
            # A small ridge keeps a class whose feature is constant invertible.
            covs[c] = np.cov(x, rowvar=False) + 1e-9 * np.eye(k)
        return cls(means, covs)

    def log_likelihood(self, features: np.ndarray) -> np.ndarray:
        """(n, c) Gaussian log-likelihood of each sample under each class."""
        n, c = features.shape[0], self.means.shape[0]
        out = np.empty((n, c))
        for j in range(c):
            inv = np.linalg.inv(self.covariances[j])
            _, logdet = np.linalg.slogdet(self.covariances[j])
            d = features - self.means[j]
            out[:, j] = -0.5 * (np.einsum("ij,jk,ik->i", d, inv, d) + logdet)
        return out

    def predict(self, features: np.ndarray) -> np.ndarray:
        """Class of largest likelihood for each sample."""
        return np.argmax(self.log_likelihood(features), axis=1)


@dataclass
class Accuracy:
    """Confusion matrix (rows reference, columns classified), overall accuracy, kappa."""

    names: list[str]
    confusion: np.ndarray
    overall: float
    kappa: float

    @classmethod
    def of(cls, reference: np.ndarray, classified: np.ndarray, names: Sequence[str]
           ) -> Accuracy:
        """The confusion matrix, overall accuracy and kappa of the ``classified`` class indices
        against the ``reference`` ones (both into ``names``)."""
        c = len(names)
        conf = np.zeros((c, c), dtype=np.int64)
        np.add.at(conf, (reference, classified), 1)
        total = conf.sum()
        overall = float(np.trace(conf) / total) if total else math.nan
        chance = float((conf.sum(axis=0) * conf.sum(axis=1)).sum() / total**2) if total else 0
        kappa = (overall - chance) / (1.0 - chance) if chance < 1 else math.nan
        return cls(list(names), conf, overall, kappa)

    def lines(self) -> list[str]:
        """The table as text: counts, then producer's and user's accuracy per class."""
        w = max(10, *(len(n) for n in self.names))
        out = [f"{'reference':<{w}} " + " ".join(f"{n:>{w}}" for n in self.names)
               + f" {'producer':>9}"]
        for i, name in enumerate(self.names):
            row = self.conf_row(i)
            out.append(f"{name:<{w}} " + " ".join(f"{v:>{w}d}" for v in row)
                       + f" {self.producer(i):>9.1%}")
        out.append(f"{'user':<{w}} " + " ".join(f"{self.user(j):>{w}.1%}"
                                                 for j in range(len(self.names))))
        out.append(f"overall accuracy {self.overall:.1%}, kappa {self.kappa:.3f}")
        return out

    def conf_row(self, i: int) -> list[int]:
        """Row ``i`` of the confusion matrix (reference class ``i``) as ints."""
        return [int(v) for v in self.confusion[i]]

    def producer(self, i: int) -> float:
        """Fraction of reference class ``i`` classified as ``i``."""
        n = self.confusion[i].sum()
        return float(self.confusion[i, i] / n) if n else math.nan

    def user(self, j: int) -> float:
        """Fraction of cells classified as ``j`` that are ``j``."""
        n = self.confusion[:, j].sum()
        return float(self.confusion[j, j] / n) if n else math.nan


def stratified_split(labels: np.ndarray, fraction: float, rng: np.random.Generator
                     ) -> np.ndarray:
    """A training mask holding ``fraction`` of the samples of every label."""
    train = np.zeros(labels.size, dtype=bool)
    for c in np.unique(labels):
        idx = np.flatnonzero(labels == c)
        take = max(1, int(round(fraction * idx.size)))
        train[rng.choice(idx, take, replace=False)] = True
    return train


def classify_cells(
    xyz: np.ndarray,
    radiometry: np.ndarray,
    labels: np.ndarray,
    *,
    names: Sequence[str],
    merge: Sequence[int] | None = None,
    merged_names: Sequence[str] | None = None,
    cell_m: float = 2.0,
    ground_window_m: float = 60.0,
    train_fraction: float = 0.3,
    seed: int = 0,
) -> Accuracy:
    """Classify raster cells of normalised DSM + one radiometric value and score them.

    Parameters
    ----------
    xyz : (n, 3) float64
        Points, map frame, metres.
    radiometry : (n,) float
        Raw intensity or reflectance per point (NaN: ignored).
    labels : (n,) int
        Reference class of every point, ``0 .. len(names) - 1``; a cell's reference is its
        majority.
    names : sequence of str
        Classes the classifier is trained on.
    merge : sequence of int, optional
        Information class of each trained class (e.g. roof and asphalt to built-up); the
        accuracy is given over the merged classes, named ``merged_names``.
    cell_m, ground_window_m : float
        Raster cell and ground window (wider than the largest building), metres.
    train_fraction : float
        Share of each class's cells used for training; the rest are scored.
    seed : int
        Seed of the training split (use the same for both radiometries).
    """
    raster, flat = Raster.covering(xyz[:, :2], cell_m)
    height = raster.normalised_dsm(flat, xyz[:, 2], ground_window_m)
    value = raster.mean(flat, np.asarray(radiometry, dtype=np.float64))
    reference = raster.majority(flat, np.asarray(labels), len(names))
    ok = np.isfinite(height) & np.isfinite(value)
    features = np.column_stack([height[ok], value[ok]])
    reference = reference[ok]
    train = stratified_split(reference, train_fraction, np.random.default_rng(seed))
    model = GaussianML.fit(features[train], reference[train], len(names))
    predicted = model.predict(features[~train])
    truth = reference[~train]
    if merge is None:
        return Accuracy.of(truth, predicted, names)
    to = np.asarray(merge)
    return Accuracy.of(to[truth], to[predicted], merged_names or [str(i) for i in
                                                                  range(int(to.max()) + 1)])


__all__ = ["Accuracy", "GaussianML", "Raster", "classify_cells", "stratified_split"]
