"""StarSurface (the composite eyes' geometry) against closed forms: on a sphere and an
ellipsoid written as radial functions, ray casts must match the analytic hits."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Ellipsoid, Sphere
from models.star_surface import StarSurface

RADII = np.array([12.0, 11.0, 10.0])


def _ellipsoid_rho(U):
    return 1.0 / np.sqrt(((U / RADII) ** 2).sum(axis=1))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(["sphere", "ellipsoid"]))
def test_ray_casts_match_the_closed_form_from_inside_and_outside(seed, kind):
    rng = np.random.default_rng(seed)
    if kind == "sphere":
        star, exact = StarSurface(lambda U: np.full(len(U), 11.5)), Sphere(np.zeros(3), 11.5)
    else:
        star, exact = StarSurface(_ellipsoid_rho), Ellipsoid(np.zeros(3), RADII)
    D = rng.normal(size=(200, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    O = rng.uniform(-7.0, 7.0, (200, 3))  # inside: the first exit
    O[150:] = 20.0 * D[150:] * -1.0 + rng.uniform(-3.0, 3.0, (50, 3))  # outside, aimed in: the first entry
    np.testing.assert_allclose(star.ray_cast(O, D), exact.ray_cast(O, D), rtol=0, atol=1e-9)


def test_a_ray_that_misses_gives_nan():
    star = StarSurface(lambda U: np.full(len(U), 10.0))
    assert np.isnan(star.ray_cast(np.array([[30.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))[0])


@pytest.mark.parametrize("n", [1, 7])
def test_ray_casts_do_not_depend_on_the_batch(n):
    star = StarSurface(_ellipsoid_rho)
    rng = np.random.default_rng(n)
    D = rng.normal(size=(21, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    O = rng.uniform(-5.0, 5.0, (21, 3))
    whole = star.ray_cast(O, D)
    parts = np.concatenate([star.ray_cast(O[k:k + n], D[k:k + n]) for k in range(0, 21, n)])
    np.testing.assert_allclose(parts, whole, rtol=0, atol=1e-12)
