"""The sample of a strip pair chosen as the surface strip's points go by
(core/calibration/bounded.py SampleChooser) against the one chosen on the whole strip's TIN."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal_ros.core.calibration.bounded import SampleChooser, StripExtent, neighbourhood_radius
from lidarcal_ros.core.calibration.pairs import footprint_keys, stratified_sample
from lidarcal_ros.core.calibration.tin import Tin, TinQuality, match_to_tin

CELL = 10.0
QUALITY = TinQuality(max_edge_m=4.0, max_slope_deg=70.0, max_bend_deg=10.0, flat_slope_deg=5.0)


def _terrain(xy: np.ndarray) -> np.ndarray:
    """Ridges and slopes of every aspect (m)."""
    x, y = xy[:, 0], xy[:, 1]
    return 6.0 * np.sin(x / 14.0) + 4.0 * np.cos(y / 9.0) + 0.02 * x


@pytest.mark.parametrize("reverse", [False, True])
def test_chosen_block_by_block_equals_chosen_on_the_whole_strip(reverse: bool) -> None:
    rng = np.random.default_rng(5)
    n = 40_000  # one point a m^2 over 400 m x 100 m, flown along x
    xy = np.column_stack([rng.uniform(0, 400, n), rng.uniform(0, 100, n)])
    xy = xy[np.argsort(-xy[:, 0] if reverse else xy[:, 0])]
    surface = np.column_stack([xy, _terrain(xy) + rng.normal(0, 0.02, n)])
    c = 3000
    cxy = np.column_stack([rng.uniform(20, 380, c), rng.uniform(20, 80, c)])
    cand = np.column_stack([cxy, _terrain(cxy) + rng.normal(0, 0.05, c)])
    index = np.arange(c) * 7  # indices into a point strip
    priority = rng.random(c)
    caps = {"per_class_cap": 60, "flat_class_factor": 4}

    # on the whole strip, as PairMatcher.choose_samples
    m = match_to_tin(cand, Tin(surface, QUALITY), surface, max_normal_distance=2.0)
    whole = stratified_sample(m, np.arange(c), priority, **caps)
    assert 200 < whole.size < c  # the classes capped

    blocks = np.array_split(np.arange(n), 200)
    extent = StripExtent(2, CELL)
    for b, rows in enumerate(blocks):
        extent.add(surface[rows], np.zeros(rows.size), block=b)
    extent.finish()
    radius = neighbourhood_radius(extent.density, spacings=8.0, margin_m=0.0)
    chooser = SampleChooser(index, cand, priority, extent.last_block_near(cxy, radius),
                            radius=radius, quality=QUALITY, threshold=2.0, cell=CELL,
                            batch=100, **caps)
    most = 0
    for b, rows in enumerate(blocks):
        chooser.offer(surface[rows], footprint_keys(surface[rows], CELL))
        most = max(most, chooser.held)
        chooser.passed(b)
    sample, xyz, before = chooser.result()
    np.testing.assert_array_equal(sample, index[whole])
    np.testing.assert_array_equal(xyz, cand[whole])
    np.testing.assert_allclose(before, m.distance[whole], atol=1e-9)
    # what waited was a band of the strip along the candidates still to match
    assert most < 0.2 * n
