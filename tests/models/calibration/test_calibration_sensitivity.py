"""Fig. 3 sensitivity: sphere-diameter error under a perturbed sensor pose.

Physics: with beams along the sphere's radii, shifting the sensor origin by delta
along the beam moves every point radially by delta, so the fitted diameter grows by
exactly 2 delta. In the paper's geometry the beams meet the retina 0-30 deg off
its normal, and the partial-cap fit shares the shift between radius and centre, so
the slope is a little less than 2. A tilt shifts the points sideways by distance x
tilt (at most 12 mm x 2 deg = 0.42 mm); that moves the cloud rather than resizing
it, so the diameter changes by far less than under an offset.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.calibration.sensitivity import (
    diameter_error_um,
    diameter_sensitivity,
    instrument_x_axes,
    reconstructed_points,
    sphere_eye,
)
from models.scan.paper_scan import Scan, paper_scan


@pytest.fixture(scope="module")
def scan():
    return paper_scan(sphere_eye(12.0), noise_um=0.0, spacing_mm=0.3)


def test_unperturbed_reconstruction_is_the_scan(scan):
    assert np.allclose(reconstructed_points(scan), scan.points)
    assert abs(diameter_error_um(scan, 12.0)) < 1e-6


@settings(max_examples=20)
@given(delta_um=st.floats(-500.0, 500.0), seed=st.integers(0, 1000))
def test_radial_beams_grow_the_diameter_by_twice_the_offset(delta_um, seed):
    rng = np.random.default_rng(seed)
    tips = rng.uniform(-3.0, 3.0, (200, 3))
    dirs = rng.normal(size=(200, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2]) - 0.1  # a posterior cap, like the scan (and no +z beam)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # beams along the radii: start each beam on the ray from the centre through the tip
    p_WT = np.linalg.norm(tips, axis=1, keepdims=True) * dirs
    d = 12.0 - np.linalg.norm(p_WT, axis=1)
    radial = Scan(p_WT, dirs, d, d)
    assert diameter_error_um(radial, 12.0, offset_mm=delta_um * 1e-3) == pytest.approx(2.0 * delta_um, abs=1e-6)


def test_paper_geometry_offset_is_linear_and_tilt_is_minor():
    c = diameter_sensitivity([-200.0, -100.0, 0.0, 100.0, 200.0], [0.0, 0.5, 2.0], radius_mm=12.0, spacing_mm=0.3)
    e = c.offset_diameter_error_um
    slope = (e[-1] - e[0]) / 400.0
    assert 1.5 < slope < 2.0
    assert np.all(np.diff(e) > 0) and abs(e[2]) < 1e-6
    assert abs(e[0] + e[-1]) < 0.01 * abs(e[-1])  # odd to first order
    t = c.tilt_diameter_error_um
    assert t.shape == (4, 3) and np.allclose(t[:, 0], 0.0, atol=1e-6)
    assert np.all(np.abs(t[:, 2]) > np.abs(t[:, 1]))  # grows with the tilt
    assert np.abs(t).max() < 0.05 * abs(e[-1])  # 2 deg matters far less than 200 um


@settings(max_examples=50)
@given(theta=st.floats(0.0, 1.5), phi=st.floats(-np.pi, np.pi))
def test_instrument_x_axis_is_a_unit_normal_to_the_beam(theta, phi):
    b = np.array([[np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)]])
    x = instrument_x_axes(b)
    assert np.linalg.norm(x) == pytest.approx(1.0, abs=1e-12)
    assert abs(x[0] @ b[0]) < 1e-12
    if theta == 0.0:
        assert np.allclose(x[0], [1.0, 0.0, 0.0])


def test_bad_arguments_name_themselves():
    with pytest.raises(ValueError, match="radius_mm"):
        sphere_eye(7.0)
    with pytest.raises(ValueError, match="offsets_um"):
        diameter_sensitivity([], [1.0])
    with pytest.raises(ValueError, match="tilts_deg"):
        diameter_sensitivity([1.0], [np.nan])
    with pytest.raises(ValueError, match="along \\+z"):
        instrument_x_axes(np.array([[0.0, 0.0, 1.0]]))
