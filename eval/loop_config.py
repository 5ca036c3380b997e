"""The closed loop's configuration: rates, the sensor's packets, the filter, the model's trust rules (Hz, s, mm, deg)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planning.instrument_points import MonitoredPointsConfig
from planning.iioct import rate_ratio
from planning.iioct.stream import StreamFault
from safety import FilterConfig
from safety.actuator import ActuatorModel
from safety.margins import UncertaintyMargins


# k of the boundary d_safe + k sigma: the local model's sigma is a standard deviation; 3 sigma
# holds 99.87 % of a normal error one-sided, and the measured 3-sigma coverage of the true
# retina (boundary.json: model.sigma3_coverage) checks it
LOCAL_SIGMA_FACTOR = 3.0


def default_filter(local_model: bool) -> FilterConfig:
    """The loop's filter settings by model: k = LOCAL_SIGMA_FACTOR on the local-global model's
    sigma, FilterConfig's own k = 1 on the quadric model's coverage misfit (its phase margins
    hold the rest of its uncertainty)."""
    return FilterConfig(sigma_factor=LOCAL_SIGMA_FACTOR) if local_model else FilterConfig()


@dataclass(frozen=True)
class LoopConfig:
    """Rates (Hz; sensor_rate_hz an integer multiple r of control_rate_hz), the sensor's
    packet (samples per delivery = per model update, a multiple of r; 20 at 2 kHz: a model
    update every 10 ms, well inside the filter's model and sensor age limits, with half
    the per-packet Drake events and Python of packets of 10), the sensor mode
    ("distance": the extractor's error model, fast; "ascan": full A-scans), the filter,
    margins and monitored points, and how often Drake's DoDifferentialInverseKinematics
    is timed on the same state for comparison (every n-th control step; 0: never).
    The filter trusts the fitted model only once it holds `model_min_points` points over
    a scan range of `model_min_scan_range_mm` (a sphere through a few points of a small
    patch can be millimetres off) and its radii lie in `model_radius_range_mm` (human
    retinas: 9.5-12.5 mm; anything else is not an eye but a bad fit); until then the
    conservative prior bounds the motion.
    Afterwards the tip or the port, further than `trust_angle_deg` (seen from the eye
    centre) from every measured direction, keeps the prior's clearance too: the fit's
    extrapolation is only as good as the eye is regular (models.adaptive.coverage); nearer, its
    margin grows by the model's measured misfit there (how far inside the model the
    retina was measured within `misfit_angle_deg`: a detachment the sphere averages away).
    With `local_model` (the default) the model is the local-global one (models.local): the
    filter keeps every point d_safe + k sigma inside it, k = filter.sigma_factor (3 by
    default here: LOCAL_SIGMA_FACTOR) and sigma its standard deviation at the point's
    direction, which replaces the phase margins, the trust angle and the misfit rule
    (used only with local_model False: the quadric boundary).
    `extra_constraints`: safety.constraints objects the filter stacks after the standard
    ones (their point groups: planning.step_kinematics.POINT_GROUPS).
    `actuator`: the robot's actuator between the filter and the joints (delay, lag,
    acceleration limit; the filter is told it); `oct_time_offset_s` (s, >= 0): the OCT
    stream's lag behind the robot's joint angles (the paper measured up to 2.6 ms);
    `encoder_noise_rad`: SD (rad) of the noise on the joint angles the sensor's points
    are reconstructed from; `stream_fault`: a degenerate iiOCT stream injected from its
    onset in each run (planning.iioct.stream; default none)."""

    control_rate_hz: float = 1000.0
    sensor_rate_hz: float = 2000.0
    sensor_packet: int = 20
    sensor_mode: str = "distance"
    filter: FilterConfig | None = None  # None: default_filter(local_model)
    margins: UncertaintyMargins = field(default_factory=UncertaintyMargins)
    points: MonitoredPointsConfig = field(default_factory=MonitoredPointsConfig)
    drake_diffik_every: int = 25
    model_min_points: int = 200
    model_min_scan_range_mm: float = 5.0
    trust_angle_deg: float = 10.0
    misfit_angle_deg: float = 10.0
    model_radius_range_mm: tuple = (8.0, 16.0)
    extra_constraints: tuple = ()
    local_model: bool = True
    actuator: ActuatorModel = field(default_factory=ActuatorModel)
    oct_time_offset_s: float = 0.0
    encoder_noise_rad: float = 0.0
    stream_fault: StreamFault = field(default_factory=StreamFault)

    def __post_init__(self):
        if self.filter is None:
            object.__setattr__(self, "filter", default_filter(self.local_model))
        for name in ("control_rate_hz", "sensor_rate_hz"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"LoopConfig.{name} must be > 0 Hz, got {v}")
        ratio = rate_ratio(self.sensor_rate_hz, self.control_rate_hz)
        if ratio is None:
            raise ValueError(f"LoopConfig.sensor_rate_hz must be an integer multiple (1, 2, 3, ... x) of "
                             f"control_rate_hz = {self.control_rate_hz:g} Hz, got {self.sensor_rate_hz:g} Hz")
        if not (isinstance(self.sensor_packet, int) and self.sensor_packet >= 1 and self.sensor_packet % ratio == 0):
            raise ValueError(f"LoopConfig.sensor_packet must be an int >= 1 and a multiple of sensor_rate_hz / "
                             f"control_rate_hz = {ratio}, got {self.sensor_packet}")
        if self.sensor_mode not in ("distance", "ascan"):
            raise ValueError(f"LoopConfig.sensor_mode must be 'distance' or 'ascan', got {self.sensor_mode!r}")
        for name in ("trust_angle_deg", "misfit_angle_deg"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 < v <= 180.0):
                raise ValueError(f"LoopConfig.{name} must be in (0, 180] deg, got {v}")
        if not (np.isfinite(self.oct_time_offset_s) and 0.0 <= self.oct_time_offset_s <= 0.1):
            raise ValueError(f"LoopConfig.oct_time_offset_s must be in [0, 0.1] s, got {self.oct_time_offset_s}")
        if not (np.isfinite(self.encoder_noise_rad) and self.encoder_noise_rad >= 0.0):
            raise ValueError(f"LoopConfig.encoder_noise_rad must be >= 0 rad, got {self.encoder_noise_rad}")
        if not (isinstance(self.drake_diffik_every, int) and self.drake_diffik_every >= 0):
            raise ValueError(f"LoopConfig.drake_diffik_every must be an int >= 0, got {self.drake_diffik_every}")
