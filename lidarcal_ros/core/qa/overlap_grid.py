"""Swath-to-swath height agreement on a grid, without patches or a trajectory.

Memory grows with the area flown, not the points (docs/internals.md, "Quality measures").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PairQA:
    """Swath-to-swath discrepancy of two overlapping strips on a grid.

    Attributes
    ----------
    strip_a, strip_b : int
    coverage : float
        Shared cells / cells of the smaller strip.
    n_cells : int
        Shared smooth cells compared.
    median_dz, rms_dz : float
        Median and robust RMS (1.4826 MAD about 0, i.e. without the median removed) of the
        mean-height differences A - B of the compared cells, metres.
    level : ``"OK"``, ``"WARN"`` or ``"ERROR"``
        RMS against 8 / 16 cm (USGS LBS QL2 swath-to-swath limits).
    """

    strip_a: int
    strip_b: int
    coverage: float
    n_cells: int
    median_dz: float
    rms_dz: float
    level: str


class OverlapGrid:
    """Per strip and cell: count, sum and sum of squares of the heights added.

    Parameters
    ----------
    cell_m : float
        Side of the square cells, metres.
    origin : (float, float)
        Map position of a cell corner, metres (any, as long as it stays the same).
    """

    def __init__(self, cell_m: float, origin: tuple[float, float]) -> None:
        self.cell = float(cell_m)
        self.origin = origin
        self.parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        self.sizes: dict[int, int] = {}

    def add(self, sid: np.ndarray, xyz: np.ndarray) -> None:
        """Add points ``xyz`` ((n, 3), map frame, metres) of the strips ``sid`` ((n,))."""
        ix = np.floor((xyz[:, 0] - self.origin[0]) / self.cell).astype(np.int64)
        iy = np.floor((xyz[:, 1] - self.origin[1]) / self.cell).astype(np.int64)
        key = (ix << 32) + (iy & 0xFFFFFFFF)
        for value in np.unique(sid):
            sel = sid == value
            k, inv = np.unique(key[sel], return_inverse=True)
            z = xyz[sel, 2]
            stats = np.zeros((k.size, 3))
            np.add.at(stats, inv, np.column_stack([np.ones_like(z), z, z * z]))
            lst = self.parts.setdefault(int(value), [])
            lst.append((k, stats))
            self.sizes[int(value)] = self.sizes.get(int(value), 0) + k.size
            if len(lst) > 16:
                self.parts[int(value)] = [self._reduce(lst)]

    @staticmethod
    def _reduce(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
        keys = np.concatenate([p[0] for p in parts])
        stats = np.concatenate([p[1] for p in parts])
        k, inv = np.unique(keys, return_inverse=True)
        out = np.zeros((k.size, 3))
        np.add.at(out, inv, stats)
        return k, out

    def pairs(self, *, max_std_m: float = 0.15, min_cells: int = 20, warn_m: float = 0.08,
              error_m: float = 0.16) -> list[PairQA]:
        """QA of every pair of strips sharing at least ``min_cells`` smooth cells."""
        grids = {}
        for sid, parts in self.parts.items():
            k, st = self._reduce(parts)
            n = st[:, 0]
            mean = st[:, 1] / n
            var = np.maximum(st[:, 2] / n - mean**2, 0.0)
            smooth = (n >= 2) & (np.sqrt(var) <= max_std_m)
            grids[sid] = (k, mean, smooth)
        out = []
        ids = sorted(grids)
        for i, a in enumerate(ids):
            ka, ma, sa = grids[a]
            for b in ids[i + 1:]:
                kb, mb, sb = grids[b]
                common, ia, ib = np.intersect1d(ka, kb, assume_unique=True,
                                                return_indices=True)
                if common.size < min_cells:
                    continue
                use = sa[ia] & sb[ib]
                if use.sum() < min_cells:
                    continue
                dz = ma[ia][use] - mb[ib][use]
                rms = float(1.4826 * np.median(np.abs(dz)))
                level = "ERROR" if rms > error_m else ("WARN" if rms > warn_m else "OK")
                out.append(PairQA(a, b, common.size / min(ka.size, kb.size), int(use.sum()),
                                  float(np.median(dz)), rms, level))
        return out


# ---------------------------------------------------------------------------- main


__all__ = ["OverlapGrid", "PairQA"]
