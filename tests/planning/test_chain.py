"""The compiled chain (planning.chain) against the Drake plant it is generated from."""
from __future__ import annotations

from xml.etree import ElementTree

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (FixedOffsetFrame, JacobianWrtVariable, PrismaticJoint, RevoluteJoint,
                                    SpatialInertia, UnitInertia)

from planning import SurgeryScenario
from planning.chain import (MM_PER_M, Chain, chain_kinematics, chain_pose_into, frame_axis_into, frame_pose,
                            frame_pose_and_jacobian, frame_position)
from planning.robot import URDF, Robot


@pytest.fixture(scope="module")
def robot():
    return Robot(SurgeryScenario())


joint_angles = st.lists(st.floats(-3.1, 3.1), min_size=6, max_size=6).map(np.array)


@settings(max_examples=60)
@given(q=joint_angles)
def test_every_frame_pose_and_jacobian_is_the_plants(robot, q):
    # the plant's own answers, in mm: the chain is exact up to rounding (1e-9 mm on ~400 mm)
    plant = robot.plant
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, q)
    for name, frame in robot._frames.items():
        X = frame.CalcPoseInWorld(context)
        R, p = robot.pose(name, q)
        np.testing.assert_allclose(R, X.rotation().matrix(), atol=1e-12)
        np.testing.assert_allclose(p, MM_PER_M * X.translation(), atol=1e-9)
        p_F = np.array([3.0, -2.0, 5.0])  # mm, fixed in the frame
        J = plant.CalcJacobianTranslationalVelocity(context, JacobianWrtVariable.kQDot, frame, p_F / MM_PER_M,
                                                    plant.world_frame(), plant.world_frame())
        np.testing.assert_allclose(robot.jacobian(name, p_F, q), MM_PER_M * J, atol=1e-9)
        Js = plant.CalcJacobianSpatialVelocity(context, JacobianWrtVariable.kQDot, frame, np.zeros(3),
                                               plant.world_frame(), plant.world_frame())
        Js[3:] *= MM_PER_M
        np.testing.assert_allclose(robot.spatial_jacobian(name, q), Js, atol=1e-9)


@settings(max_examples=60)
@given(q=joint_angles)
def test_the_product_without_the_jacobian_is_chain_kinematics_bit_for_bit(robot, q):
    R, p = np.full((3, 3), np.nan), np.full(3, np.nan)  # overwritten in place
    chain_pose_into(robot.chain.S, q, R, p, np.empty((2, 3, 3)))
    R_ref, p_ref, _ = chain_kinematics(robot.chain.S, q)
    assert R.tobytes() == R_ref.tobytes() and p.tobytes() == p_ref.tobytes()


@settings(max_examples=60)
@given(q=joint_angles)
def test_a_frames_pose_position_and_axes_are_the_full_products_bit_for_bit(robot, q):
    # the tip's and the sensor's home poses: frame_pose, frame_position (the loop's command
    # source's tip, every step) and frame_axis_into (the sensor's beams) against the pose
    # frame_pose_and_jacobian gives from chain_kinematics' product, the Jacobian's pass
    S = robot.chain.S
    for name in ("T", "S"):
        R_home, p_home = robot.chain.homes[name]
        R_ref, p_ref = frame_pose_and_jacobian(S, q, R_home, p_home)[:2]
        R, p = frame_pose(S, q, R_home, p_home)
        assert R.tobytes() == R_ref.tobytes() and p.tobytes() == p_ref.tobytes()
        assert frame_position(S, q, R_home, p_home).tobytes() == p_ref.tobytes()
        R_q, p_q = np.empty((3, 3)), np.empty(3)
        chain_pose_into(S, q, R_q, p_q, np.empty((2, 3, 3)))
        O, U = np.empty((3, 3)), np.empty((3, 3))
        for axis in range(3):
            frame_axis_into(R_q, p_q, R_home, p_home, axis, O, U, axis)
        assert U.T.tobytes() == R_ref.tobytes() and all(o.tobytes() == p_ref.tobytes() for o in O)


def test_world_fixed_frames_do_not_move(robot):
    assert robot.chain.fixed == {"E", "C"}
    np.testing.assert_allclose(robot.pose("C", np.full(6, 0.4))[1], robot.p_WC, atol=1e-9)
    assert not robot.spatial_jacobian("E", np.full(6, 0.4)).any()


def _two_link_plant(frame_on_first_link: bool, prismatic: bool = False):
    """A plant with two revolute joints (the second prismatic with `prismatic`) and a
    frame on the first or the second link."""
    plant = MultibodyPlant(0.0)
    inertia = SpatialInertia(1.0, np.zeros(3), UnitInertia.SolidSphere(0.1))
    a, b = plant.AddRigidBody("a", inertia), plant.AddRigidBody("b", inertia)
    plant.AddJoint(RevoluteJoint("j1", plant.world_frame(), a.body_frame(), [0.0, 0.0, 1.0]))
    second = PrismaticJoint if prismatic else RevoluteJoint
    plant.AddJoint(second("j2", a.body_frame(), b.body_frame(), [0.0, 1.0, 0.0]))
    frame = plant.AddFrame(FixedOffsetFrame("f", a if frame_on_first_link else b, RigidTransform([0.1, 0.0, 0.0])))
    plant.Finalize()
    return plant, frame


def test_a_frame_that_not_every_joint_moves_is_refused():
    plant, frame = _two_link_plant(frame_on_first_link=False)
    chain = Chain(plant, {"f": frame})
    context = plant.CreateDefaultContext()
    q = np.array([0.7, -1.1])
    plant.SetPositions(context, q)
    np.testing.assert_allclose(chain.pose("f", q)[1], MM_PER_M * frame.CalcPoseInWorld(context).translation(), atol=1e-9)
    plant, frame = _two_link_plant(frame_on_first_link=True)
    with pytest.raises(ValueError, match="moves with some joints only"):
        Chain(plant, {"f": frame})


def test_a_joint_that_is_not_revolute_is_refused():
    plant, frame = _two_link_plant(frame_on_first_link=False, prismatic=True)
    with pytest.raises(ValueError, match="revolute joint per position"):
        Chain(plant, {"f": frame})


def test_the_screw_axes_are_the_urdfs_joint_axes_through_their_origins(robot):
    """Read off meca500.urdf's text: its revolute joints, in order, have no rotation in
    their origins, so at q = 0 joint i's frame sits at the sum of the origins up to it
    (m -> mm) and its axis is the URDF's axis in W: S = (w, p x w)."""
    root = ElementTree.parse(URDF).getroot()
    joints = [j for j in root.iter("joint") if j.get("type") == "revolute"]
    assert len(joints) == 6 and all(j.find("origin").get("rpy") is None for j in joints)
    p = MM_PER_M * np.cumsum([[float(x) for x in j.find("origin").get("xyz").split()] for j in joints], axis=0)
    w = np.array([[float(x) for x in j.find("axis").get("xyz").split()] for j in joints])
    np.testing.assert_allclose(robot.chain.S, np.vstack([w.T, np.cross(p, w).T]), atol=1e-12)
