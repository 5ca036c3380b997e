"""The paper's Archimedean spiral: r = b theta / (2 pi), b = 0.5 mm, 18 revolutions,
points 0.1 mm apart along the curve (about 5,090 points, facts.md)."""
from __future__ import annotations

import numpy as np
import pytest

from models.scan.spiral import archimedean_spiral


def arc_length(theta, b):
    """Closed form: s = a/2 (theta sqrt(1 + theta^2) + asinh(theta)), a = b / (2 pi)."""
    a = b / (2 * np.pi)
    return 0.5 * a * (theta * np.sqrt(1 + theta**2) + np.arcsinh(theta))


def unwrapped_theta(P):
    return np.unwrap(np.arctan2(P[:, 1], P[:, 0]))


def test_paper_spiral_count_extent_and_equal_arc_spacing():
    P = archimedean_spiral()
    total = arc_length(36 * np.pi, 0.5)
    assert len(P) == int(np.ceil(total / 0.1)) + 1  # every 0.1 mm from the centre, and the end
    assert 5080 <= len(P) <= 5100
    np.testing.assert_allclose(P[0], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(P[-1]), 9.0, atol=1e-9)  # 18 turns of 0.5 mm
    theta = unwrapped_theta(P[1:])
    r = np.linalg.norm(P[1:], axis=1)
    np.testing.assert_allclose(r, 0.5 * theta / (2 * np.pi), atol=1e-9)  # on the spiral
    s = arc_length(theta, 0.5)
    np.testing.assert_allclose(s[:-1], 0.1 * np.arange(1, len(P) - 1), atol=1e-6)  # sub-um arc spacing
    assert s[-1] - s[-2] <= 0.1 + 1e-6


@pytest.mark.parametrize("kwargs", [{"pitch_mm": 1.0, "revolutions": 3.0, "spacing_mm": 0.05}, {"revolutions": 2.5}])
def test_other_parameters(kwargs):
    b = kwargs.get("pitch_mm", 0.5)
    rev = kwargs.get("revolutions", 18.0)
    ds = kwargs.get("spacing_mm", 0.1)
    P = archimedean_spiral(**kwargs)
    assert np.linalg.norm(P[-1]) == pytest.approx(b * rev, abs=1e-9)
    s = arc_length(unwrapped_theta(P[1:]), b)
    np.testing.assert_allclose(np.diff(s)[:-1], ds, atol=1e-6)


@pytest.mark.parametrize("name", ["pitch_mm", "revolutions", "spacing_mm"])
@pytest.mark.parametrize("value", [0.0, -1.0, np.nan, np.inf])
def test_bad_parameters_are_refused_naming_them(name, value):
    with pytest.raises(ValueError, match=name):
        archimedean_spiral(**{name: value})
