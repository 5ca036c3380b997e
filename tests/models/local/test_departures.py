"""The departures' variance (models.local.departures.spread_departures): what the pairs
within the neighbour table give, and a departing edge node's own extrapolation."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.adaptive.coverage import fibonacci_directions
from models.local.departures import FAINT_SUPPORT, neighbour_table, spread_departures
from models.local.config import LocalConfig
from models.local.geometry import node_frames

CFG = LocalConfig()
REACH, CROSS, EDGE = np.radians(CFG.departure_deg), np.radians(CFG.blend_deg), np.radians(CFG.spacing_deg)
FAINT = FAINT_SUPPORT * np.radians(CFG.support_deg)
FLOOR = CFG.departure_floor_mm


def spread(dirs, x, has, excess, dev, slope, near, table, near_table=None):
    near_table = table if near_table is None else near_table
    return spread_departures(dirs, node_frames(dirs), x, has, excess, dev, slope, near, EDGE, FAINT, REACH, FLOOR, CROSS, *table, *near_table,
                             np.zeros(len(dirs)))


@settings(max_examples=20)
@given(st.integers(0, 2**32 - 1))
def test_the_neighbour_table_loses_no_pair_that_counts(seed):
    """Random data nodes, departures, slopes and quadratics on a 600-node grid: the tables
    within 25 deg (departing nodes) and 4.8 deg (the others) give the same variances as a
    table of every pair (angles past the departure's reach and the blend add nothing), to
    the last bit."""
    rng = np.random.default_rng(seed)
    dirs = fibonacci_directions(600)
    n = len(dirs)
    has = (rng.random(n) < 0.3).astype(float)
    x = np.zeros((n, 6))
    x[:, 0] = 12.0 + rng.normal(0.0, 0.3, n)
    x[:, 1:] = rng.normal(0.0, 0.5, (n, 5))
    excess = rng.random(n) * 0.01 * has
    dev = rng.normal(0.0, 0.5, n) * has
    slope = rng.normal(0.0, 2.0, (n, 2))
    near = np.cos(rng.uniform(0.0, np.radians(10.0), n))
    args = (dirs, x, has, excess, dev, slope, near)
    every = neighbour_table(dirs, np.pi)
    np.testing.assert_array_equal(spread(*args, neighbour_table(dirs, REACH), neighbour_table(dirs, CROSS)),
                                  spread(*args, every))


@pytest.mark.parametrize("slope_sign", [1.0, -1.0])
def test_a_departing_edge_node_holds_its_own_extrapolation(slope_sign):
    """One data node, 1 mm off the global quadric, its nearest datum 5 deg away (an edge
    node: one grid spacing is 3 deg), its departure changing at 0.5 mm/rad: its variance
    beyond its posterior is (0.5 x 5 deg)^2, whichever way the rise goes; alone, no other
    data node changes it."""
    dirs = fibonacci_directions(600)
    n = len(dirs)
    k = 123
    has, dev, near = np.zeros(n), np.zeros(n), np.ones(n)
    has[k], dev[k], near[k] = 1.0, 1.0, np.cos(np.radians(5.0))
    slope = np.zeros((n, 2))
    slope[k] = (0.3 * slope_sign, 0.4 * slope_sign)
    x = np.zeros((n, 6))
    x[k, 0] = 13.0
    out = spread(dirs, x, has, np.zeros(n), dev, slope, near, neighbour_table(dirs, REACH), neighbour_table(dirs, CROSS))
    assert out[k] == pytest.approx((0.5 * np.radians(5.0)) ** 2, rel=1e-12)
    # nodes without data near it take the departure's variance (up to 25 deg), none further
    angle = np.arccos(np.clip(dirs @ dirs[k], -1.0, 1.0))
    assert np.all(out[(angle > REACH) & (has == 0)] == 0.0)
    assert np.all(out[(angle < np.radians(10.0)) & (angle > 0)] > 0.0)


def _scan_lines(radius_of, lift_mm=0.0):
    """Noise-free points r(u) u (N, 3) mm, less `lift_mm` along u, on three parallel scan
    lines 0-60 deg off the posterior pole, 15 deg apart: most nodes with data have them
    off to one side (the loop's spiral leaves its rings ~3 mm apart)."""
    a = np.radians(np.linspace(-60.0, 60.0, 1200))
    U = np.concatenate([np.stack([np.sin(a) * np.cos(b), np.full_like(a, np.sin(b)), -np.cos(a) * np.cos(b)], axis=1)
                        for b in np.radians([-15.0, 0.0, 15.0])])  # unit rows
    return (radius_of(U) - lift_mm)[:, None] * U


@pytest.mark.parametrize("lift_mm", [0.0, 0.3])
def test_a_node_s_departure_is_its_data_s_residual_from_the_global_quadric(lift_mm):
    """The emmetropic retina's ellipsoid 1 mm off the model's centre, whose radius about
    that centre changes by up to ~1.4 mm/rad: on its scan lines the nodes with data depart
    from it by -lift_mm (0: the retina on the quadric; 0.3: that much nearer the centre),
    within 1 um at the median and 25 um at worst (nodes whose data lie at the 12 deg
    support's edge: the quadric's second-order expansion there misses its third-order
    terms, 19 um here). The data's mean radius less the quadric's radius at the node,
    0.45 mm off at worst here and 28 um at the median, is not a departure."""
    from models import Ellipsoid
    from models.eyes.catalog import EMMETROPIC_RADII_MM
    from models.local.grid import LocalRetinaModel

    ellipsoid = Ellipsoid(np.array([0.6, -0.3, 0.7]), EMMETROPIC_RADII_MM)
    radius_of = lambda U: ellipsoid.ray_cast(np.zeros_like(U), U)  # noqa: E731  (from the model's centre)
    P = _scan_lines(radius_of, lift_mm)
    m = LocalRetinaModel(np.zeros(3))
    for k in range(0, len(P), 20):
        m.update(P[k:k + 20], ellipsoid)
    m.solve_all()
    data = m._has != 0.0
    assert data.sum() > 200
    error = np.abs(m._dev[data] + lift_mm)
    assert np.median(error) < 1e-3 and error.max() < 0.025
