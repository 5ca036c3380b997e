"""A beam held on one spot (models.adaptive.dwell): the model takes a moving scan whole and
a still beam's first DWELL_MAX_POINTS A-scans per spot, so resting the instrument does not
pull the fits towards where it rests."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from models import AdaptiveEyeModel, fit_sphere
from models.adaptive.dwell import DWELL_MAX_POINTS, DWELL_RADIUS_MM, dwell_keep, new_state
from models.adaptive.transition import PredictiveCriteria
from models.eyes import make_eye
from models.local.grid import LocalRetinaModel
from models.scan.paper_scan import paper_scan

NOISE_MM = 0.02  # the sensor's distance noise (design.md)


def _keep(P):
    keep = np.empty(len(P), dtype=np.bool_)
    n = dwell_keep(np.ascontiguousarray(P, dtype=float), new_state(), DWELL_RADIUS_MM, DWELL_MAX_POINTS, keep)
    return keep, n


def test_a_scan_moving_at_4_mm_s_or_faster_is_taken_whole():
    """2 um between A-scans (4 mm/s at 2 kHz) with the sensor's noise along the beam: every point taken."""
    rng = np.random.default_rng(0)
    s = 0.002 * np.arange(20_000)
    P = np.column_stack([s, np.zeros_like(s), 11.0 + rng.normal(0.0, NOISE_MM, len(s))])
    keep, n = _keep(P)
    assert n == len(P) and keep.all()


def test_a_still_beam_gives_its_first_points_and_then_none_until_it_moves():
    rng = np.random.default_rng(1)
    still = np.array([0.0, 0.0, 11.0]) + rng.normal(0.0, NOISE_MM, (5_000, 3))
    moved = still + np.array([1.0, 0.0, 0.0])  # the beam moves on by 1 mm, then rests again
    keep, n = _keep(np.vstack([still, moved]))
    assert n == 2 * DWELL_MAX_POINTS
    assert keep[:DWELL_MAX_POINTS].all() and not keep[DWELL_MAX_POINTS:5_000].any()
    assert keep[5_000:5_000 + DWELL_MAX_POINTS].all()


def test_non_finite_points_are_passed_on_for_the_update_to_count():
    P = np.array([[0.0, 0.0, 11.0], [np.nan, 0.0, 11.0], [np.inf, np.inf, np.inf]])
    keep, n = _keep(P)
    assert n == 3 and keep.all()


@settings(max_examples=200)
@given(st.lists(st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)), min_size=1, max_size=400))
def test_no_spot_gives_more_than_the_cap_in_a_row_and_a_point_beyond_the_radius_is_taken(xy):
    """Against a plain reading of the rule: the anchor is the first point of each run of
    points within the radius of it; a run gives at most the cap."""
    P = np.array([[x, y, 11.0] for x, y in xy])
    keep, n = _keep(P)
    anchor, count = None, 0
    for p, k in zip(P, keep):
        if anchor is None or np.linalg.norm(p - anchor) > DWELL_RADIUS_MM:
            anchor, count = p, 0
        assert k == (count < DWELL_MAX_POINTS)
        count += k
    assert n == keep.sum()


def test_a_beam_resting_on_a_pathology_weighs_what_a_pass_over_it_would():
    """The emmetropic eye's paper spiral, then 20,000 A-scans (10 s) at one spot 1.5 mm
    inside its retina (a detachment's top the beam rests on): the model ends exactly as
    with the first 100 of them (what a 4 mm/s pass gives a 0.2 mm stretch), where the
    least-squares sphere of the spiral and all the resting points lies 0.3 mm or more from
    the spiral's own (taken whole, a resting beam outweighs the scan)."""
    eye = make_eye("emmetropic")
    P = paper_scan(eye, seed=0).points
    spot = P[-1] * (1.0 - 1.5 / np.linalg.norm(P[-1]))
    rest = spot + np.random.default_rng(2).normal(0.0, NOISE_MM, (20_000, 3))
    assert abs(fit_sphere(np.vstack([P, rest])).radius - fit_sphere(P).radius) > 0.3
    models = []
    for tail in (rest, rest[:DWELL_MAX_POINTS]):
        m = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
        for Q in (P, tail):
            for i in range(0, len(Q), 20):
                m.update(Q[i:i + 20])
        models.append(m)
    held, passed = models
    assert held.n_dwelling == len(rest) - DWELL_MAX_POINTS and passed.n_dwelling == 0
    assert len(held.last_accepted) == 0  # what the loop's coverage and log take from the last update
    assert held.kind == passed.kind and held.sphere.radius == passed.sphere.radius
    np.testing.assert_array_equal(held.ellipsoid.radii, passed.ellipsoid.radii)
    np.testing.assert_array_equal(held.globe.last_ok.radii, passed.globe.last_ok.radii)
