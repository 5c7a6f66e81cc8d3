"""The two Delaunay backends of the TINs give the same triangulation.

Triangle (Shewchuk's, through the ``triangle`` package) is used when installed; it is free for
non-commercial use only, so a user may remove it and get scipy's qhull instead (README,
"Licences"). Both must then give the same triangles, neighbours and patch quality.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from lidarcal_ros.core.calibration import tin
from lidarcal_ros.core.simulation.simulate import simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec

pytestmark = pytest.mark.skipif(tin._triangle is None, reason="the 'triangle' package is absent")

Triangle = tuple[int, int, int]


def _by_vertices(simplices: np.ndarray, neighbors: np.ndarray
                 ) -> dict[Triangle, dict[int, Triangle | None]]:
    """Each triangle (sorted vertex ids) with, per vertex, the triangle across the opposite
    edge (None on the hull): independent of the order and orientation a backend uses."""
    def key(k: int) -> Triangle:
        a, b, c = sorted(int(v) for v in simplices[k])
        return a, b, c

    return {key(k): {int(v): (key(int(n)) if n >= 0 else None)
                     for v, n in zip(simplices[k], neighbors[k], strict=True)}
            for k in range(len(simplices))}


@pytest.mark.parametrize("layout", ["random", "scan lines"])
def test_triangle_and_qhull_triangulate_alike(layout: str) -> None:
    rng = np.random.default_rng(5)
    if layout == "random":
        xy = rng.uniform(-200.0, 200.0, size=(4000, 2))
    else:  # along-track rows of a scanner, slightly irregular (no four points cocircular)
        across, along = np.meshgrid(np.linspace(-300, 300, 120), np.arange(40) * 1.7)
        xy = np.column_stack([across.ravel(), along.ravel()]) + rng.normal(0, 0.05, (4800, 2))
    by_triangle = _by_vertices(*tin.delaunay(xy, backend=tin.TinBackend.TRIANGLE))
    by_qhull = _by_vertices(*tin.delaunay(xy, backend=tin.TinBackend.SCIPY))
    assert len(by_triangle) > 1.9 * len(xy)  # 2n - 2 - (points on the hull)
    assert by_triangle == by_qhull


def test_a_strip_tin_without_triangle_is_the_same(monkeypatch: Any) -> None:
    spec = SimulationSpec.from_options(density=0.1, line_length_m=150.0, seed=3)
    strip = simulate_mission(spec).mission.strips[0]
    quality = tin.TinQuality()
    with_triangle = tin.Tin(strip.xyz, quality)
    monkeypatch.setattr(tin, "_triangle", None)  # as where the package is not installed
    with_qhull = tin.Tin(strip.xyz, quality)

    def judged(t: tin.Tin) -> dict[Triangle, tuple[bool, bool]]:
        out = {}
        for k, simplex in enumerate(t.simplices):
            a, b, c = sorted(int(v) for v in simplex)
            out[a, b, c] = (bool(t.usable[k]), bool(t.sloped[k]))
        return out

    assert judged(with_triangle) == judged(with_qhull)
    assert 0 < with_qhull.usable.mean() < 1
    # and points are found in the same triangles
    probe = strip.xyz[::7, :2] + 0.01
    found_a = with_triangle.locate(probe)
    found_b = with_qhull.locate(probe)
    assert (found_a >= 0).mean() > 0.9
    same = [tuple(sorted(with_triangle.simplices[i])) == tuple(sorted(with_qhull.simplices[j]))
            for i, j in zip(found_a, found_b, strict=True) if i >= 0 and j >= 0]
    assert all(same) and len(same) == int((found_a >= 0).sum())
