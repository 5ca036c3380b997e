"""The simulated iiOCT sensor on the robot: the sensor model (`IioctSensor`), its packet
types, the compiled packet kernels and the joint-angle register (the extractor's error
model it draws from is models.iioct.error_model). The sensor's Drake system is eval.systems.sensor.IioctSensorSystem.

Units: mm, s, rad; frame W.
"""
from planning.iioct.kernels import DISTANCE_MODE_CONFIDENCE
from planning.iioct.latches import JointRegister, rate_ratio
from planning.iioct.packet import BAD_JOINT_STATE, NO_SAMPLE_YET, SensorPacket, SensorSample
from planning.iioct.sensor import DEFAULT_MAX_INCIDENCE_RAD, IioctSensor

__all__ = [
    "BAD_JOINT_STATE",
    "DEFAULT_MAX_INCIDENCE_RAD",
    "DISTANCE_MODE_CONFIDENCE",
    "NO_SAMPLE_YET",
    "IioctSensor",
    "JointRegister",
    "SensorPacket",
    "SensorSample",
    "rate_ratio",
]
