"""The simulated iiOCT sensor on the robot: the sensor model (`IioctSensor`), its packet
types, the extractor's error model, the compiled packet kernels and the joint-angle
register. The sensor's Drake system is eval.systems.sensor.IioctSensorSystem.

Units: mm, s, rad; frame W.
"""
from planning.iioct.error_model import ExtractorErrorModel, extractor_error_model
from planning.iioct.kernels import DISTANCE_MODE_CONFIDENCE
from planning.iioct.latches import JointRegister, rate_ratio
from planning.iioct.packet import BAD_JOINT_STATE, NO_SAMPLE_YET, SensorPacket, SensorSample
from planning.iioct.sensor import DEFAULT_MAX_INCIDENCE_RAD, IioctSensor

__all__ = [
    "BAD_JOINT_STATE",
    "DEFAULT_MAX_INCIDENCE_RAD",
    "DISTANCE_MODE_CONFIDENCE",
    "NO_SAMPLE_YET",
    "ExtractorErrorModel",
    "IioctSensor",
    "JointRegister",
    "SensorPacket",
    "SensorSample",
    "extractor_error_model",
    "rate_ratio",
]
