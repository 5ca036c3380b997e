"""Ellipsoid geometry: exact signed distance (Eberly) against brute force, gradients,
closest points, ray casting, argument checks.

Reference bounds (derived in tests/conftest.py): with h the covering radius of a dense
surface sampling and d the exact distance, every sample lies on the surface, so
|d| <= d_ref; the sample nearest the true closest point x* lies within h of it and, the
ellipsoid being convex with curvature <= kappa_max = r_max / r_min^2 (Blaschke's rolling
ball), d_ref^2 <= d^2 + h^2 inside and d_ref^2 <= d^2 + h^2 (1 + kappa_max |d|) outside.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from models import Ellipsoid

ROUND_OFF_MM = 1e-9  # float64 on eye-sized coordinates (~1e-14 relative), with a wide margin

CYCLE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # a proper rotation with exact entries
GENERIC = Rotation.from_euler("zyx", [0.7, -0.4, 1.1]).as_matrix()
CASES = {
    "emmetropic": Ellipsoid(np.zeros(3), [11.455, 11.365, 10.148]),
    "triaxial 2:1, axes permuted, decentred": Ellipsoid([4.0, -7.0, 30.0], [6.0, 12.0, 9.0], CYCLE),
    "triaxial 2:1, rotated, decentred": Ellipsoid([4.0, -7.0, 30.0], [6.0, 12.0, 9.0], GENERIC),
    "prolate spheroid": Ellipsoid([-1.0, 2.0, 0.5], [8.0, 8.0, 13.0], CYCLE),
    "oblate spheroid": Ellipsoid([0.0, 0.0, 0.0], [12.0, 12.0, 7.0]),
}
# Cases whose axis coordinates are exact in float64: on-axis and in-plane queries stay
# exactly on the axes/planes. In a generic rotation they land ~1e-16 mm off them, which
# is what test_distance_is_continuous_across_the_plane_of_the_shortest_axis holds to.
EXACT_AXES = [name for name, e in CASES.items() if np.all(np.isin(e.rotation, (-1.0, 0.0, 1.0)))]


def local_to_frame(e: Ellipsoid, L: np.ndarray) -> np.ndarray:
    """Points given in e's axis coordinates (mm) -> e's frame."""
    return e.center + L @ e.rotation.T


def implicit_value(e: Ellipsoid, X: np.ndarray) -> np.ndarray:
    """sum (l_i / r_i)^2 - 1 in e's axis coordinates: 0 on the surface, < 0 inside."""
    L = (X - e.center) @ e.rotation / e.radii
    return np.sum(L * L, axis=1) - 1.0


def query_points(e: Ellipsoid, seed: int = 0) -> np.ndarray:
    """Random points in and around e, points on every axis (inside, on, outside), the
    centre, points near the surface and far away."""
    rng = np.random.default_rng(seed)
    r = e.radii
    box = rng.uniform(-1.6, 1.6, (1500, 3)) * r
    axes = np.concatenate([np.outer(s * np.array([0.0, 0.3, 0.6, 0.95, 1.0, 1.05, 1.5, 3.0]), np.eye(3)[i]) * r[i]
                           for i in range(3) for s in (-1.0, 1.0)])
    plane = rng.uniform(-1.2, 1.2, (200, 3)) * r * (1.0 - np.eye(3)[np.argmin(r)])  # in the plane of the shortest axis
    U = rng.normal(size=(300, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    near = U * r / np.linalg.norm(U / r, axis=1, keepdims=True) * (1 + rng.uniform(-0.01, 0.01, (300, 1)))
    far = U[:50] * rng.uniform(100.0, 1000.0, (50, 1))
    special = [axes, plane] if np.all(np.isin(e.rotation, (-1.0, 0.0, 1.0))) else []
    return local_to_frame(e, np.vstack([box, *special, near, far, np.zeros((1, 3))]))


@pytest.mark.parametrize("name", sorted(CASES))
def test_signed_distance_matches_brute_force_within_the_sampling_error(name, brute_force_distance):
    e = CASES[name]
    Q = query_points(e)
    d = e.signed_distance(Q)
    d_ref, h = brute_force_distance(e.center, e.radii, e.rotation, Q)
    assert h < 0.06  # the sampling is as dense as intended
    kappa = e.radii.max() / e.radii.min() ** 2
    outside = d < 0
    upper = np.sqrt(d * d + h * h * (1.0 + np.where(outside, kappa * np.abs(d), 0.0)))
    assert np.all(np.abs(d) <= d_ref + ROUND_OFF_MM)
    assert np.all(d_ref <= upper + ROUND_OFF_MM)
    # sign: > 0 inside, < 0 outside
    v = implicit_value(e, Q)
    strict = np.abs(v) > 1e-12
    assert np.all(np.sign(d[strict]) == -np.sign(v[strict]))


@pytest.mark.parametrize("name", sorted(CASES))
def test_distance_at_the_centre_is_the_smallest_semi_axis(name):
    e = CASES[name]
    assert e.signed_distance(e.center)[0] == pytest.approx(e.radii.min(), abs=ROUND_OFF_MM)
    np.testing.assert_allclose(abs(implicit_value(e, e.closest_point(e.center))), 0.0, atol=1e-12)


@pytest.mark.parametrize("name", EXACT_AXES)
def test_points_on_the_axes_have_the_analytic_distance(name):
    e = CASES[name]
    r = e.radii
    for i in range(3):
        for s in (-1.0, 1.0):
            for f in (1.0, 1.2, 4.0):  # on and outside: the axis end is the closest point
                q = local_to_frame(e, s * f * r[i] * np.eye(3)[i])
                assert e.signed_distance(q)[0] == pytest.approx(-(f - 1.0) * r[i], abs=ROUND_OFF_MM)
    # inside on the longest axis: the axis end while the query lies beyond the centre of
    # curvature there (rho = c^2 / a); deeper, the closest point leaves the axis:
    # x = x0 a^2 / (a^2 - c^2), d^2 = (x - x0)^2 + c^2 (1 - x^2 / a^2).
    i_a, i_c = np.argmax(r), np.argmin(r)
    a, c = r[i_a], r[i_c]
    if a - c > 1e-3:
        for x0 in np.linspace(0.0, a, 23):
            q = local_to_frame(e, x0 * np.eye(3)[i_a])
            x = x0 * a * a / (a * a - c * c)
            expected = a - x0 if x >= a else np.sqrt((x - x0) ** 2 + c * c * (1.0 - x * x / (a * a)))
            assert e.signed_distance(q)[0] == pytest.approx(expected, abs=ROUND_OFF_MM)
    # inside on the shortest axis: the nearer end of that axis
    for x0 in np.linspace(0.0, c, 7):
        q = local_to_frame(e, -x0 * np.eye(3)[i_c])
        assert e.signed_distance(q)[0] == pytest.approx(c - x0, abs=ROUND_OFF_MM)


@pytest.mark.parametrize("name", sorted(CASES))
def test_closest_point_is_on_the_surface_at_the_signed_distance_along_the_normal(name):
    e = CASES[name]
    Q = query_points(e, seed=1)
    X = e.closest_point(Q)
    np.testing.assert_allclose(implicit_value(e, X), 0.0, atol=1e-12)
    d = e.signed_distance(Q)
    np.testing.assert_allclose(np.linalg.norm(Q - X, axis=1), np.abs(d), rtol=0, atol=ROUND_OFF_MM)
    # optimality: q - x is normal to the surface at x (first-order condition)
    n = (X - e.center) @ e.rotation / e.radii**2 @ e.rotation.T
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    V = Q - X
    assert np.all(np.linalg.norm(np.cross(V, n), axis=1) <= 1e-9 * np.maximum(1.0, np.linalg.norm(V, axis=1)))


@pytest.mark.parametrize("name", sorted(CASES))
def test_gradient_is_a_unit_vector_that_matches_finite_differences(name):
    e = CASES[name]
    Q = query_points(e, seed=2)
    d = e.signed_distance(Q)
    # away from the medial axis: every maximal inscribed ball there is larger than the
    # smallest radius of curvature r_min^2 / r_max (rolling-ball theorem)
    Q = Q[d < 0.5 * e.radii.min() ** 2 / e.radii.max()][:400]
    G = e.gradient(Q)
    np.testing.assert_allclose(np.linalg.norm(G, axis=1), 1.0, atol=1e-12)
    step = 1e-5  # central differences: truncation ~ step^2 kappa^2, round-off ~ 1e-16 |x| / step
    fd = np.stack(
        [(e.signed_distance(Q + step * u) - e.signed_distance(Q - step * u)) / (2 * step) for u in np.eye(3)], axis=1
    )
    np.testing.assert_allclose(G, fd, rtol=0, atol=1e-7)
    # direction of increasing distance: towards the inside
    assert np.all(e.signed_distance(Q + 1e-3 * G) > e.signed_distance(Q))


@pytest.mark.parametrize("radii", [[12.0, 9.0, 6.0], [13.0, 8.0, 8.0], [11.455, 11.365, 10.148]])
def test_distance_is_continuous_across_the_plane_of_the_shortest_axis(radii):
    """The distance is 1-Lipschitz: moving the query by delta changes it by <= delta. Points
    a rotation leaves ~1e-16 mm off the plane of the shortest axis must not break it."""
    e = Ellipsoid(np.zeros(3), radii)
    i_c = int(np.argmin(e.radii))
    base = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, -1.0, 0.0]])[:, [0, 1, 2]]
    base = np.roll(base, i_c - 2, axis=1)  # zero coordinate along the shortest axis
    d0 = e.signed_distance(base)
    for delta in (1e-300, 1e-16, 1e-13, 1e-10, 1e-8, 1e-6):
        d = e.signed_distance(base + delta * np.eye(3)[i_c])
        assert np.all(np.abs(d - d0) <= delta + ROUND_OFF_MM)


def distance_and_gradient_via_closest_point(e: Ellipsoid, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The signed distance and unit gradient from Ellipsoid.closest_point (NumPy): |Q - X|,
    signed by the implicit value, and the normalised inward normal -R (x / radii^2) at X."""
    X = e.closest_point(Q)
    d = np.linalg.norm(Q - X, axis=1)
    n = -(((X - e.center) @ e.rotation / e.radii**2) @ e.rotation.T)
    return np.where(implicit_value(e, Q) < 0.0, d, -d), n / np.linalg.norm(n, axis=1, keepdims=True)


@settings(max_examples=40)
@given(st.integers(0, 2**32 - 1), st.floats(1e-6, 3.0), st.integers(0, 2**32 - 1))
def test_compiled_query_equals_the_closest_point_construction(rot_seed, scale, seed):
    # the compiled query and the closest-point path are the same construction: equal to
    # rounding, near and far, inside and out, with a point exactly on the smallest axis's
    # plane
    rng = np.random.default_rng(seed)
    e = Ellipsoid(rng.normal(0.0, 3.0, 3), rng.uniform(5.0, 15.0, 3), Rotation.random(random_state=rot_seed).as_matrix())
    Q = e.center + scale * rng.normal(0.0, 8.0, (40, 3))
    Q[0] = e.center + e.rotation[:, np.argsort(e.radii)[1:]] @ [2.0, 1.0]  # on the smallest axis's plane
    d, g = e.signed_distance_and_gradient(Q)
    d_ref, g_ref = distance_and_gradient_via_closest_point(e, Q)
    np.testing.assert_allclose(d, d_ref, atol=1e-10)
    np.testing.assert_allclose(g[1:], g_ref[1:], atol=1e-9)
    # on the plane the closest points off it come in a mirrored pair (a tie that rounding
    # in either path may break either way): the normals agree up to that reflection
    s = e.rotation[:, np.argmin(e.radii)]
    np.testing.assert_allclose(abs(g[0] @ s), abs(g_ref[0] @ s), atol=1e-9)
    np.testing.assert_allclose(g[0] - (g[0] @ s) * s, g_ref[0] - (g_ref[0] @ s) * s, atol=1e-9)


@settings(max_examples=30)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 3.0), st.integers(0, 2**32 - 1))
def test_ray_hits_lie_on_the_surface_and_are_the_first_crossing(rot_seed, offset, seed):
    rng = np.random.default_rng(seed)
    e = Ellipsoid(rng.uniform(-50, 50, 3), rng.uniform(6.0, 12.0, 3), Rotation.random(random_state=rot_seed).as_matrix())
    D = rng.normal(size=(200, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    inside = local_to_frame(e, rng.uniform(-0.5, 0.5, (100, 3)) * e.radii)
    outside = local_to_frame(e, (1.0 + offset) * 2.0 * e.radii * np.sign(rng.normal(size=(100, 3))))
    O = np.vstack([inside, outside])
    D[100:] = local_to_frame(e, rng.uniform(-0.5, 0.5, (100, 3)) * e.radii) - O[100:]  # aimed inside: hits
    D[100:] /= np.linalg.norm(D[100:], axis=1, keepdims=True)
    t = e.ray_cast(O, D)
    assert np.all(np.isfinite(t)) and np.all(t > 0)
    hits = O + t[:, None] * D
    np.testing.assert_allclose(e.signed_distance(hits), 0.0, atol=ROUND_OFF_MM)
    # first crossing: the ray stays on its starting side before t
    for frac in (0.25, 0.5, 0.9, 0.999):
        sd = e.signed_distance(O + frac * t[:, None] * D)
        assert np.all(sd[:100] > 0) and np.all(sd[100:] < 0)


def test_rays_that_miss_or_point_away_give_nan():
    e = CASES["emmetropic"]
    O = np.array([[0.0, 0.0, 30.0], [0.0, 0.0, 30.0], [0.0, 20.0, 0.0]])
    D = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.all(np.isnan(e.ray_cast(O, D)))
    np.testing.assert_allclose(e.ray_cast(O[:1], -D[:1]), [30.0 - 10.148], atol=ROUND_OFF_MM)


def test_ray_cast_refuses_mismatched_shapes():
    with pytest.raises(ValueError, match="origins and dirs"):
        CASES["emmetropic"].ray_cast(np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0]]))


# ---- construction and bad input ------------------------------------------------------------

def test_volume_and_immutability():
    e = CASES["triaxial 2:1, rotated, decentred"]
    assert e.volume == pytest.approx(4.0 / 3.0 * np.pi * 6.0 * 12.0 * 9.0, rel=1e-15)
    with pytest.raises(ValueError):
        e.center[0] = 1.0  # read-only arrays


@pytest.mark.parametrize("radii", [[10.0, 0.0, 9.0], [10.0, -1.0, 9.0], [10.0, np.nan, 9.0], [10.0, np.inf, 9.0], [10.0, 9.0]])
def test_bad_radii_are_refused(radii):
    with pytest.raises(ValueError, match="radii"):
        Ellipsoid(np.zeros(3), radii)


@pytest.mark.parametrize("center", [[0.0, np.nan, 0.0], [0.0, 0.0], [np.inf, 0.0, 0.0]])
def test_bad_centre_is_refused(center):
    with pytest.raises(ValueError, match="center"):
        Ellipsoid(center, [10.0, 9.0, 8.0])


@pytest.mark.parametrize(
    "rotation, why",
    [
        (np.diag([1.0, 1.0, -1.0]), "reflection"),
        (np.diag([1.0, 1.0, 1.001]), "orthonormal"),
        (np.eye(3) + 1e-3 * np.triu(np.ones((3, 3)), 1), "orthonormal"),
        (np.eye(2), "shape"),
        (np.full((3, 3), np.nan), "finite"),
    ],
)
def test_non_rotations_are_refused(rotation, why):
    with pytest.raises(ValueError, match=f"rotation.*{why}|rotation must be a .*{why}"):
        Ellipsoid(np.zeros(3), [10.0, 9.0, 8.0], rotation)


@pytest.mark.parametrize("Q", [np.zeros((4, 2)), np.zeros((2, 3, 3)), [[0.0, np.nan, 0.0]], [[np.inf, 0.0, 0.0]]])
def test_bad_query_points_are_refused(Q):
    e = CASES["emmetropic"]
    for method in (e.signed_distance, e.gradient, e.closest_point):
        with pytest.raises(ValueError, match="Q"):
            method(Q)


@pytest.mark.parametrize("name", list(CASES))
def test_of_fit_holds_read_only_copies_like_the_checked_constructor(name):
    """Ellipsoid.of_fit (for a fit's arrays, unchecked) holds exactly what the checked
    constructor holds: equal read-only copies, which later writes to the arrays it was
    given leave alone; or, given read-only arrays (the per-packet update's), those arrays."""
    e = CASES[name]
    c, r, R = e.center.copy(), e.radii.copy(), e.rotation.copy()
    fit = Ellipsoid.of_fit(c, r, R)
    c[:], r[:], R[:] = 0.0, 1.0, 0.0
    for field in ("center", "radii", "rotation"):
        a = getattr(fit, field)
        np.testing.assert_array_equal(a, getattr(e, field))
        assert not a.flags.writeable and a.dtype == np.float64
    Q = query_points(e)
    np.testing.assert_array_equal(fit.signed_distance(Q), e.signed_distance(Q))
    frozen = [e.center.copy(), e.radii.copy(), e.rotation.copy()]  # read-only arrays: held as they are
    for a in frozen:
        a.setflags(write=False)
    held = Ellipsoid.of_fit(*frozen)
    assert all(getattr(held, f) is a for f, a in zip(("center", "radii", "rotation"), frozen))
    np.testing.assert_array_equal(held.signed_distance(Q), e.signed_distance(Q))
