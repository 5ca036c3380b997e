"""Measured directions: covered bins, angles from the data, cheap rebuilds."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from models.coverage import DirectionCoverage, fibonacci_directions


def test_fibonacci_directions_are_unit_and_even():
    D = fibonacci_directions(4000)
    np.testing.assert_allclose(np.linalg.norm(D, axis=1), 1.0)
    assert abs(D.mean(axis=0)).max() < 1e-3


@given(st.floats(0.0, 80.0), st.floats(0.0, 2 * np.pi))
def test_the_angle_from_a_measured_cap_is_the_angle_past_its_rim(off_deg, azimuth):
    """Data over a 30 deg cap about -z: a direction at 30 + off deg from -z is off deg
    from the data, within the 2 deg bins' spacing."""
    c = np.array([1.0, 2.0, 3.0])
    cov = DirectionCoverage(c, bin_deg=2.0)
    D = fibonacci_directions(20000)
    cap = D[D[:, 2] <= -np.cos(np.radians(30.0))]
    cov.add(c + 11.0 * cap)
    th = np.radians(30.0 + off_deg)
    q = c + 5.0 * np.array([np.sin(th) * np.cos(azimuth), np.sin(th) * np.sin(azimuth), -np.cos(th)])
    angle = np.degrees(cov.view().angle_from_data_rad(q[None])[0])
    assert angle == pytest.approx(off_deg, abs=2.5)


def test_no_data_means_no_trust_and_bad_input_is_refused():
    cov = DirectionCoverage(np.zeros(3))
    assert cov.view().angle_from_data_rad(np.array([[1.0, 0.0, 0.0]]))[0] == pytest.approx(np.pi)
    cov.add(np.array([[np.nan, 0.0, 0.0]]))
    assert cov.view().n_covered == 0
    with pytest.raises(ValueError, match="bin_deg"):
        DirectionCoverage(np.zeros(3), bin_deg=0.0)
