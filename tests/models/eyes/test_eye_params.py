"""Shape parameters of the composite eyes: names and ranges checked in one line each, and a
parameter that is passed really changes the retina by the amount it names."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.eyes import EYE_PARAMS, check_eye_params, make_eye


def test_every_parameter_has_a_default_inside_its_range():
    for shape, params in EYE_PARAMS.items():
        for name, (lo, hi, default) in params.items():
            assert lo < default <= hi, (shape, name)
            assert check_eye_params(shape, {name: default}) == {name: default}


@pytest.mark.parametrize("shape, params, words", [
    ("detached", {"apex_offset_mm": 3.0}, ["'apex_offset_mm'", "height_mm (0, 5] mm", "angle_deg [0, 90] deg"]),
    ("emmetropic", {"height_mm": 1.0}, ["no shape parameters"]),
    ("staphyloma", {"depth_mm": 0.0}, ["depth_mm must be in (0, 4] mm", "got 0.0"]),
    ("detached", {"angle_deg": 91.0}, ["angle_deg must be in [0, 90] deg"]),
    ("pointed", {"apex_offset_mm": float("nan")}, ["apex_offset_mm must be in (0, 6] mm"]),
])
def test_a_wrong_name_or_value_is_one_line_naming_it_and_its_range(shape, params, words):
    with pytest.raises(ValueError) as exc:
        make_eye(shape, **params)
    msg = str(exc.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


@settings(max_examples=15)
@given(height=st.floats(0.5, 3.5), angle=st.floats(0.0, 65.0))
def test_a_detachment_lifts_the_retina_by_its_height_at_its_centre(height, angle):
    a = np.radians(angle)
    u = np.array([[0.0, -np.sin(a), -np.cos(a)]])  # inferior of the posterior pole
    healthy = np.linalg.norm(make_eye("myopic").surface_points(u)[0])
    lifted = np.linalg.norm(make_eye("detached", height_mm=height, angle_deg=angle).surface_points(u)[0])
    assert healthy - lifted == pytest.approx(height, abs=1e-9)


@settings(max_examples=15)
@given(depth=st.floats(1.0, 3.0), apex=st.floats(2.0, 4.0))
def test_staphyloma_depth_and_pointed_apex_move_the_wall_outward_by_their_size(depth, apex):
    pole = np.array([[0.0, 0.0, -1.0]])
    myopic = np.linalg.norm(make_eye("myopic").surface_points(pole)[0])
    # the pointed eye's apex lies apex_offset_mm behind the myopic posterior pole, on the axis
    assert np.linalg.norm(make_eye("pointed", apex_offset_mm=apex).surface_points(pole)[0]) - myopic == pytest.approx(apex, abs=1e-9)
    a = np.radians(15.0)
    u = np.array([[np.sin(a), 0.0, -np.cos(a)]])
    base = np.linalg.norm(make_eye("myopic").surface_points(u)[0])
    # the outpouching's far wall lies depth_mm beyond the retina along its centre (a C1 blend of
    # width 1 mm only adds where the walls meet, far from the centre)
    deep = np.linalg.norm(make_eye("staphyloma", depth_mm=depth).surface_points(u)[0])
    assert deep - base == pytest.approx(depth, abs=1e-6)
