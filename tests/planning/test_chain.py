"""The compiled chain (planning.chain) against the Drake plant it was read from."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import FixedOffsetFrame, JacobianWrtVariable, RevoluteJoint, SpatialInertia, UnitInertia

from planning import SurgeryScenario
from planning.chain import MM_PER_M, Chain, _apply, chain_kinematics, chain_pose_into, frame_pose, frame_position
from planning.robot import Robot


@pytest.fixture(scope="module")
def robot():
    return Robot(SurgeryScenario())


joint_angles = st.lists(st.floats(-3.1, 3.1), min_size=6, max_size=6).map(np.array)


@settings(max_examples=60, deadline=None)
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


@settings(max_examples=60, deadline=None)
@given(q=joint_angles)
def test_the_product_without_the_jacobian_is_chain_kinematics_bit_for_bit(robot, q):
    R, p = np.full((3, 3), np.nan), np.full(3, np.nan)  # overwritten in place
    chain_pose_into(robot.chain.S, q, R, p, np.empty((2, 3, 3)))
    R_ref, p_ref, _ = chain_kinematics(robot.chain.S, q)
    assert R.tobytes() == R_ref.tobytes() and p.tobytes() == p_ref.tobytes()


@settings(max_examples=60, deadline=None)
@given(q=joint_angles)
def test_a_frames_pose_and_position_are_the_full_products_bit_for_bit(robot, q):
    # the tip's home pose: frame_pose and frame_position (the loop's command source's tip,
    # every step) against _apply on chain_kinematics' product, the Jacobian's pass
    S, (R_home, p_home) = robot.chain.S, robot.chain.homes["T"]
    R_ref, p_ref = _apply(*chain_kinematics(S, q)[:2], R_home, p_home)
    R, p = frame_pose(S, q, R_home, p_home)
    assert R.tobytes() == R_ref.tobytes() and p.tobytes() == p_ref.tobytes()
    assert frame_position(S, q, R_home, p_home).tobytes() == p_ref.tobytes()


def test_world_fixed_frames_do_not_move(robot):
    assert robot.chain.fixed == {"E", "C"}
    np.testing.assert_allclose(robot.pose("C", np.full(6, 0.4))[1], robot.p_WC, atol=1e-9)
    assert not robot.spatial_jacobian("E", np.full(6, 0.4)).any()


def _two_link_plant(frame_on_first_link: bool):
    """A plant with two revolute joints and a frame on the first or the second link."""
    plant = MultibodyPlant(0.0)
    inertia = SpatialInertia(1.0, np.zeros(3), UnitInertia.SolidSphere(0.1))
    a, b = plant.AddRigidBody("a", inertia), plant.AddRigidBody("b", inertia)
    plant.AddJoint(RevoluteJoint("j1", plant.world_frame(), a.body_frame(), [0.0, 0.0, 1.0]))
    plant.AddJoint(RevoluteJoint("j2", a.body_frame(), b.body_frame(), [0.0, 1.0, 0.0]))
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
