"""The safety filter's constraints, one rule per module (safety.constraints.base says what a constraint is)."""
from safety.constraints.base import CONTEXT, Constraint
from safety.constraints.joint_limits import JointPositionLimits
from safety.constraints.joint_speed import JointSpeedLimits
from safety.constraints.keep_out import KeepOut
from safety.constraints.linear_equality import LinearEquality
from safety.constraints.point_barrier import PointBarrier
from safety.constraints.rcm import RcmEquality
from safety.constraints.tip_speed import TipSpeedLimit

__all__ = ["CONTEXT", "Constraint", "JointPositionLimits", "JointSpeedLimits", "KeepOut", "LinearEquality",
           "PointBarrier", "RcmEquality", "TipSpeedLimit"]
