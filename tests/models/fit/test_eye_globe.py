"""The eye globe (models.fit.eye_globe): the eye's ellipsoid nearest a scatter matrix and
known wall points, and its place under the local model."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from models import AdaptiveEyeModel, Ellipsoid
from models.adaptive.model import EYE_AXIS_RATIO_MAX, EYE_RADII_MM, eyes_radii
from models.adaptive.transition import PredictiveCriteria
from models.eyes import make_eye
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.fit.eye_globe import EyeGlobe
from models.fit.quadric_kernels import add_design_rows
from models.local.grid import LocalRetinaModel
from models.scan.paper_scan import paper_scan


def _scatter(P, p0):
    S = np.zeros((10, 10))
    add_design_rows(S, P, p0, LENGTH_SCALE_MM)
    return S


def _refits(g: EyeGlobe, P, center, radius, rotation, n: int = 30) -> None:
    """n refits on the scatter matrix of P, as a stream's every 20 points (the same points:
    the candidates' steps converge)."""
    S = _scatter(P, P[0])
    for k in range(n):
        g.refit(S, P[0], len(P) + 20 * k, center, radius, rotation)


def _cap(ell: Ellipsoid, z_max: float, n: int = 40) -> np.ndarray:
    """Points of `ell` posterior of z_max in its own frame (a scan's cap), in W."""
    return ell.sample_surface(n, n, z_max=z_max)


@settings(max_examples=15, deadline=None)
@given(a=st.floats(10.0, 12.5), b=st.floats(10.0, 12.5), c=st.floats(10.0, 12.5), yaw=st.floats(-0.3, 0.3))
def test_an_eyes_ellipsoid_seen_over_its_posterior_half_is_found(a, b, c, yaw):
    """Noise-free points of an eye's ellipsoid (within the bounds) posterior of its equator:
    the globe is that ellipsoid; tolerance 0.05 mm on the semi-axes (the LM's stopping,
    not the model: the cost at the truth is 0)."""
    if max(a, b, c) > EYE_AXIS_RATIO_MAX * min(a, b, c):
        return
    truth = Ellipsoid(np.array([1.0, -2.0, 3.0]), np.array([a, b, c]), Rotation.from_euler("z", yaw).as_matrix())
    P = _cap(truth, 0.0)
    g = EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX)
    _refits(g, P, P.mean(axis=0) + np.array([0, 0, 5.0]), 10.0, np.eye(3))
    assert g.ellipsoid is not None
    err = np.abs(g.ellipsoid.signed_distance(truth.sample_surface(20, 20)))
    assert err.max() < 0.05


def test_its_semi_axes_are_an_eyes_on_a_pointed_pole():
    """The pointed eye's posterior paraboloid fits no eye's ellipsoid: the globe's semi-axes
    stay within EYE_RADII_MM and their ratio within EYE_AXIS_RATIO_MAX (eyes_radii)."""
    eye = make_eye("pointed")
    P = paper_scan(eye, seed=0).points
    P = P[np.isfinite(P).all(axis=1)]
    g = EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX)
    _refits(g, P, P.mean(axis=0) + np.array([0, 0, 5.0]), 10.0, np.eye(3))
    assert eyes_radii(*g.ellipsoid.radii.tolist())
    assert g.ellipsoid.radii.max() > 1.2 * g.ellipsoid.radii.min()  # at the ratio's bound: the pole pulls it


def test_a_wall_point_pins_the_globe_in_front_of_the_scan():
    """A cap of a sphere of 11 mm seen to 60 deg from its pole, and a wall point on a wider
    eye's equator: with the point the globe passes within 0.1 mm of it; without, it does
    not (it is the sphere, 1 mm inside it)."""
    truth = Ellipsoid(np.zeros(3), np.array([11.0, 11.0, 11.0]))
    P = _cap(truth, -5.5)
    wall = np.array([[12.0, 0.0, 0.0]])
    for W, near in ((None, False), (wall, True)):
        g = EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX, W)
        _refits(g, P, np.zeros(3), 11.0, np.eye(3))
        d = abs(float(g.ellipsoid.signed_distance(wall)[0]))
        assert (d < 0.1) == near, d


def test_it_is_published_only_while_it_fits_better_than_the_sphere():
    """Streamed the pointed eye's paper spiral 20 points at a time, the scatter matrix
    growing: after every refit the published globe's cost (data and wall point, mm^2) is
    below the sphere's on the same matrix, and a globe is published by the end."""
    from models import fit_sphere

    eye = make_eye("pointed")
    P = paper_scan(eye, seed=0).points
    P = P[np.isfinite(P).all(axis=1)]
    wall = eye.pose.p_WE + np.array([[0.0, 11.5, 5.0]])
    g = EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX, wall)
    S = np.zeros((10, 10))
    for i in range(0, 3000, 20):
        add_design_rows(S, P[i:i + 20], P[0], LENGTH_SCALE_MM)
        if i < 400:
            continue
        s = fit_sphere(P[:i + 20])
        g.refit(S, P[0], i + 20, s.center, s.radius, np.eye(3))
        if g.ellipsoid is not None:
            r = float(np.clip(s.radius, *EYE_RADII_MM))
            sphere = g.cost_of(S, P[0], s.center, [r, r, r], np.eye(3))
            assert g.cost_mm2 < sphere
    assert g.ellipsoid is not None


@pytest.mark.parametrize("wall", [[[0.0, np.nan, 0.0]], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0], [[0.0, 1.0]], [[[0.0, 1.0, 2.0]]]])
def test_bad_wall_points_are_refused(wall):
    """Non-finite points and any shape but (3,) or (K, 3): one line naming wall_W."""
    with pytest.raises(ValueError, match="wall_W"):
        EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX, wall)


def test_one_wall_point_may_be_given_as_a_vector():
    assert EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX, [1.0, 2.0, 3.0]).wall.shape == (1, 3)


def test_under_the_local_model_it_replaces_the_sphere_on_the_pointed_eye():
    """On the pointed eye's paper spiral the least-squares ellipsoid is no eye's: the
    quadric under the local model is the eye globe, with the sphere's prior (sd inf), and
    over the reference region it lies nearer the true retina than the sphere fit (the
    sphere's MAE ~2 mm there; the globe's without a wall point ~0.9 mm: asserted < 0.75 x)."""
    eye = make_eye("pointed")
    scan = paper_scan(eye, seed=0)
    m = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(eye.pose.p_WE))
    for i in range(0, len(scan.points), 20):
        m.update(scan.points[i:i + 20], scan.beam_W[i:i + 20])
    g, trend, sd = m.quadrics_for_local()
    assert g is m.eye_globe.ellipsoid and trend is m.ellipsoid and sd == np.inf
    T = eye.reference_samples(60, 60)
    assert np.abs(g.signed_distance(T)).mean() < 0.75 * np.abs(m.sphere.signed_distance(T)).mean()
