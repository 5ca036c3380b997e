"""The prior eye lies inside every simulated retina, wherever the eye sits within the
placement uncertainty; margins follow the model phase."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.eyes import EYE_SHAPES, EyePose, make_eye
from safety.margins import UncertaintyMargins, conservative_prior


@settings(max_examples=12)
@given(st.sampled_from(EYE_SHAPES), st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3), st.floats(-15, 15))
def test_prior_is_inside_every_retina(shape, offset, tilt_deg):
    offset = np.asarray(offset)
    if np.linalg.norm(offset) > 1.0:
        offset = offset / np.linalg.norm(offset)
    eye = make_eye(shape, EyePose.anatomical(tilt_deg=tilt_deg, nasal_mm=0.0, inferior_mm=0.0))
    eye.pose = EyePose(eye.pose.R_WE, offset)  # true centre within 1 mm of the nominal origin
    prior = conservative_prior(np.zeros(3))
    surface = prior.sample_surface(24, 48)
    # every point of the prior surface is inside the true retina, with the 0.5 mm reserve
    assert eye.signed_distance(surface).min() >= 0.5 - 1e-6


def test_margins_by_phase():
    m = UncertaintyMargins()
    assert m.margin_mm(None) == 0.0
    assert m.margin_mm("sphere") == 1.0
    assert m.margin_mm("ellipsoid", 0.02) == pytest.approx(0.05 + 3 * 0.02)
    with pytest.raises(ValueError, match="kind"):
        m.margin_mm("cube")
    with pytest.raises(ValueError, match="sphere_mm"):
        UncertaintyMargins(sphere_mm=-1)
