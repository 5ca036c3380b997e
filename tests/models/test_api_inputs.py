"""Bad arguments to the models' and the filter's constructors and queries: a ValueError
naming the argument and its range, never a silent wrong answer or an error from deep
inside NumPy or numba."""
from __future__ import annotations

import numpy as np
import pytest

from models import Ellipsoid, Sphere
from models.adaptive.model_field import ModelField
from models.eyes import make_eye
from models.local.field import LocalField

SPHERE = Sphere(np.zeros(3), 12.0)


@pytest.mark.parametrize("value, says", [("abc", "must be a number in (0, 6] mm, got 'abc'"), (None, "got None"),
                                         ([2.0], "got [2.0]"), (True, "got True"), ("2", "got '2'")])
def test_make_eye_refuses_a_parameter_that_is_no_number(value, says):
    with pytest.raises(ValueError, match=r"pointed apex_offset_mm .*" + "".join("\\" + c if c in "()[]" else c for c in says)):
        make_eye("pointed", apex_offset_mm=value)


def test_make_eye_refuses_a_pose_that_is_no_pose():
    with pytest.raises(ValueError, match="pose must be a models.eyes.EyePose or None, got str"):
        make_eye("detached", "x")


@pytest.mark.parametrize("params", [np.zeros(5), np.zeros(40), np.zeros((2, 60))])
def test_local_field_refuses_params_that_are_no_models(params):
    with pytest.raises(ValueError, match="LocalField: params must be a LocalRetinaModel's params"):
        LocalField(params)


@pytest.mark.parametrize("center, says", [(np.zeros(2), "center"), ([np.nan, 0, 0], "center"),
                                          ([30.0, 0, 0], "must lie inside the shape")])
def test_an_exact_local_field_needs_a_centre_inside_its_shape(center, says):
    with pytest.raises(ValueError, match=says):
        LocalField.exact(Ellipsoid(np.zeros(3), [11.4, 11.3, 10.1], np.eye(3)), center)


@pytest.mark.parametrize("P", [np.arange(6.0), np.zeros((2, 6)), np.zeros((4, 2))])
def test_model_field_refuses_points_that_are_not_n_by_3(P):
    with pytest.raises(ValueError, match=r"P must be an \(N, 3\)"):
        ModelField(SPHERE, 0.2).signed_distance(P)


@pytest.mark.parametrize("kw, says", [(dict(trust_angle_rad=np.nan), "trust_angle_rad must be in (0, pi]"),
                                      (dict(trust_angle_rad=-1.0), "trust_angle_rad"),
                                      (dict(misfit_angle_rad=0.0), "misfit_angle_rad must be in (0, pi]")])
def test_model_field_refuses_angles_out_of_range(kw, says):
    with pytest.raises(ValueError, match=says.replace("(", r"\(").replace("]", r"\]")):
        ModelField(SPHERE, 0.2, **kw)


def test_model_field_refuses_a_shape_that_is_no_quadric():
    with pytest.raises(ValueError, match="ModelField.shape must be a models.Sphere, a models.Ellipsoid or None, got str"):
        ModelField("sphere")


def test_the_filters_constraints_refuse_what_they_cannot_hold():
    from safety import FilterConfig
    from safety.constraints import JointPositionLimits, LinearEquality, PointBarrier

    with pytest.raises(ValueError, match="q_min and q_max must not be NaN"):
        JointPositionLimits(np.array([np.nan, 0.0]), np.array([1.0, 1.0]))
    with pytest.raises(ValueError, match="A and b must be finite"):
        LinearEquality(np.array([[np.nan, 1.0]]), np.array([0.0]))
    with pytest.raises(ValueError, match="max_points must be an int >= 1"):
        PointBarrier("boundary", "eye", max_points=-5)
    with pytest.raises(ValueError, match="FilterConfig.solver must be 'daqp' or an installed qpsolvers solver"):
        FilterConfig(solver="bogus")
    assert FilterConfig(solver="clarabel").solver == "clarabel"


@pytest.mark.parametrize("cast", [lambda d: SPHERE.ray_cast(np.zeros(3), d),
                                  lambda d: Ellipsoid(np.zeros(3), [11.4, 11.3, 10.1], np.eye(3)).ray_cast(np.zeros(3), d),
                                  lambda d: make_eye("detached").ray_cast(np.zeros(3), d)])
@pytest.mark.parametrize("direction", [[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
def test_every_shape_casts_unit_rays_only(cast, direction):
    """A zero or non-unit direction gave the sphere 12 mm and the ellipsoid 5.7 mm (the
    distance in units of its length); every shape refuses it as the eyes did."""
    with pytest.raises(ValueError, match=r"dirs must be unit vectors"):
        cast(np.array(direction))
    assert cast(np.array([0.0, 0.0, 1.0]))[0] > 9.0


def test_an_unknown_robot_frame_is_named():
    from planning import Robot, SurgeryScenario

    robot = Robot(SurgeryScenario())
    with pytest.raises(ValueError, match="unknown frame 'nosuch'; the frames are"):
        robot.pose("nosuch", np.zeros(6))
