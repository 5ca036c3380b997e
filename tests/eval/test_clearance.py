"""eval.clearance: each step's smallest true clearance (true_clearances) and the largest
excess of the barrier's bounds over the true clearance (bound_excess), bit for bit what
searching every point gives, from fewer searches."""
import numpy as np
from hypothesis import given, settings, strategies as st

from eval.clearance import bound_excess, true_clearances
from models.eyes import make_eye


class CountingEye:
    """A sphere of radius 12 mm about the origin (signed distance 12 - |p|, > 0 inside),
    counting the points it is asked about."""

    def __init__(self):
        self.asked = 0

    def signed_distance(self, Q):
        Q = np.asarray(Q, dtype=float)
        self.asked += len(Q)
        return 12.0 - np.linalg.norm(Q, axis=1)


def _every_point(points_W, eye):
    counts = np.array([len(p) for p in points_W])
    d = eye.signed_distance(np.vstack(points_W))
    return np.minimum.reduceat(d, np.concatenate([[0], np.cumsum(counts)[:-1]]))


def _instrument_path(rng, steps, counts, speed_mm_per_step):
    """A tip wandering inside the eye and points along a shaft from it towards a trocar."""
    tip = np.array([0.0, 0.0, -6.0])
    trocar = np.array([0.0, 11.0, 5.0])
    out = []
    for k in counts[:steps]:
        tip = tip + rng.normal(scale=speed_mm_per_step, size=3)
        tip *= min(1.0, 11.9 / np.linalg.norm(tip))
        s = np.linspace(0.0, 0.8, k)[:, None]
        out.append(tip + s * (trocar - tip))
    return out


@settings(max_examples=60)
@given(seed=st.integers(0, 2**32 - 1), steps=st.integers(1, 200), speed=st.floats(1e-4, 0.5),
       switch=st.integers(0, 200))
def test_equals_searching_every_point(seed, steps, speed, switch):
    rng = np.random.default_rng(seed)
    counts = [4 if i < switch else 5 for i in range(steps)]  # the shaft's samples change mid-run
    pts = _instrument_path(rng, steps, counts, speed)
    eye = CountingEye()
    np.testing.assert_array_equal(true_clearances(pts, eye), _every_point(pts, CountingEye()))
    assert eye.asked <= sum(counts)


def test_searches_far_fewer_points_on_a_slow_instrument():
    """0.01 mm per step (10 mm/s at 1 kHz) with 4 points: the anchors (1 step in 10) and
    about one point per other step, so under half of the points."""
    pts = _instrument_path(np.random.default_rng(1), 500, [4] * 500, 0.01)
    eye = CountingEye()
    true_clearances(pts, eye)
    assert eye.asked < 0.5 * 4 * 500


def test_a_non_finite_point_makes_its_step_nan_only():
    pts = _instrument_path(np.random.default_rng(2), 30, [4] * 30, 0.05)
    pts[7] = pts[7].copy()
    pts[7][2, 0] = np.nan
    d = true_clearances(pts, CountingEye())
    assert np.isnan(d[7]) and np.isfinite(np.delete(d, 7)).all()
    np.testing.assert_array_equal(np.delete(d, 7), np.delete(_every_point(pts, CountingEye()), 7))


def test_composite_eye_same_minima():
    """The detached eye's closest-point search (models.eyes.star_surface) on a run near the
    bump: the same minima as searching every point."""
    eye = make_eye("detached")
    rng = np.random.default_rng(3)
    p_WE = eye.pose.p_WE
    pts = [p + p_WE + np.array([0.0, 0.0, -4.0]) for p in _instrument_path(rng, 60, [4] * 60, 0.05)]
    np.testing.assert_array_equal(true_clearances(pts, eye), _every_point(pts, eye))


def test_no_steps():
    assert true_clearances([], CountingEye()).shape == (0,)


def _bounds(rng, pts, eye, spread_mm):
    """Per step, each point's true clearance plus noise of `spread_mm` (a bound that is
    sometimes over the truth), one point in five without a bound (+inf)."""
    out = []
    for P in pts:
        b = eye.signed_distance(P) + rng.normal(scale=spread_mm, size=len(P)) - 0.5 * spread_mm
        b[rng.random(len(P)) < 0.2] = np.inf
        out.append(b)
    return out


@settings(max_examples=60)
@given(seed=st.integers(0, 2**32 - 1), steps=st.integers(1, 200), speed=st.floats(1e-4, 0.5),
       switch=st.integers(0, 200), spread=st.floats(1e-3, 1.0), cap=st.floats(0.0, 12.0))
def test_bound_excess_equals_searching_every_point(seed, steps, speed, switch, spread, cap):
    rng = np.random.default_rng(seed)
    counts = [4 if i < switch else 5 for i in range(steps)]
    pts = _instrument_path(rng, steps, counts, speed)
    bounds = _bounds(rng, pts, CountingEye(), spread)
    eye = CountingEye()
    results = bound_excess(pts, bounds, eye, (np.inf, cap))
    assert eye.asked <= sum(counts)
    for c, (best, step, clearance) in zip((np.inf, cap), results):
        every = [np.where(np.isfinite(b) & (b <= c), b - CountingEye().signed_distance(P), -np.inf)
                 for P, b in zip(pts, bounds)]
        k = int(np.argmax([e.max() for e in every]))
        if not np.isfinite(every[k].max()):
            assert (best, step) == (-np.inf, -1)
            continue
        assert best == every[k].max() and step == k
        assert clearance == CountingEye().signed_distance(pts[k])[int(np.argmax(every[k]))]


def test_bound_excess_searches_few_points_when_the_bounds_hold():
    """Bounds 0.2 mm under the truth on a slow instrument: the anchors and the few points
    within an anchor gap of the largest excess are searched."""
    rng = np.random.default_rng(4)
    pts = _instrument_path(rng, 500, [4] * 500, 0.01)
    bounds = [CountingEye().signed_distance(P) - 0.2 - 0.1 * rng.random(4) for P in pts]
    eye = CountingEye()
    [(best, _, _)] = bound_excess(pts, bounds, eye)
    assert -0.3 <= best <= -0.2 and eye.asked < 0.5 * 4 * 500
