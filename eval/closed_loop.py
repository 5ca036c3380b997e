"""The closed loop as a Drake diagram: command -> safety filter -> integrator -> sensor -> model.

    FilterSystem (1 kHz: calls the command source on the joint angles it filters, then
        filters the command; zero-order hold of qdot)
        --qdot--> DiscreteTimeIntegrator (q_{k+1} = q_k + dt qdot_k) --q--> everything
    q --> IioctSensorSystem (2 kHz: beam from the TRUE sensor pose on the TRUE eye; point
          from the reported angles and the CALIBRATED sensor pose; q latched at the
          control rate, at which the integrator's q changes)
      --packet--> AdaptiveModelSystem (updates the AdaptiveEyeModel with each packet's
          valid points) --snapshot--> FilterSystem

The command source (eval.commands) is called inside the filter's control step, on the
same joint angles: the command the filter sees is the one made for the state it filters
(no step of latency), and a control step is one Drake event, not two.
Before the model has a shape the conservative prior eye (safety.margins) bounds the
motion; the filter adds the model phase's margin (UncertaintyMargins). The filter's
inputs and outputs of every step go to the run's MCAP log (RunLogger) so that
`vitreoguard replay` re-runs them bit for bit, and every step's monitored points are
kept so that their TRUE clearance is evaluated afterwards, vectorised (LoopRun).

The systems hold Python objects that change during a simulation (the model, the
command source, the records): one simulation at a time per ClosedLoop, reset by `run`.
Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import gc
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import DiscreteTimeIntegrator

from eval.control_step import CompiledStep
from models import AdaptiveEyeModel
from models.coverage import DirectionCoverage
from models.transition import PredictiveCriteria
from planning.chain import frame_position
from planning.diffik import DrakeDiffIK
from planning.instrument_points import MonitoredPointsConfig, instrument_points
from planning.iioct_sensor import NO_SAMPLE_YET, IioctSensor, IioctSensorSystem, rate_ratio
from planning.robot import Robot
from planning.scan import start_posture
from safety import FilterConfig, FilterInputs, PointKinematics, SafetyFilter
from safety.margins import UncertaintyMargins, conservative_prior

JOINT_NAMES = tuple(f"J{k}" for k in range(1, 7))
ASCAN_LOG_EVERY = 100  # log one A-scan in 100 ("ascan" sensor mode): 20 Hz of the 2 kHz stream, ~0.4 MB/s


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
    extrapolation is only as good as the eye is regular (models.coverage); nearer, its
    margin grows by the model's measured misfit there (how far inside the model the
    retina was measured within `misfit_angle_deg`: a detachment the sphere averages away)."""

    control_rate_hz: float = 1000.0
    sensor_rate_hz: float = 2000.0
    sensor_packet: int = 20
    sensor_mode: str = "distance"
    filter: FilterConfig = field(default_factory=FilterConfig)
    margins: UncertaintyMargins = field(default_factory=UncertaintyMargins)
    points: MonitoredPointsConfig = field(default_factory=MonitoredPointsConfig)
    drake_diffik_every: int = 10
    model_min_points: int = 200
    model_min_scan_range_mm: float = 5.0
    trust_angle_deg: float = 10.0
    misfit_angle_deg: float = 10.0
    model_radius_range_mm: tuple = (8.0, 16.0)

    def __post_init__(self):
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
        if not (isinstance(self.drake_diffik_every, int) and self.drake_diffik_every >= 0):
            raise ValueError(f"LoopConfig.drake_diffik_every must be an int >= 0, got {self.drake_diffik_every}")


class ModelSnapshot(NamedTuple):
    """What the filter reads of the model: `kind` "prior" | "sphere" | "ellipsoid", its
    `shape` in W (None for the prior), `t_s` of the newest sensor sample the model system
    has processed (it stamps every packet: the filter's model age and sensor age), the
    model's RMS residual (mm) and point count."""

    kind: str
    shape: object
    t_s: float
    residual_mm: float
    n_points: int
    coverage: object = None  # models.coverage.CoverageView of the measured directions

    def __deepcopy__(self, memo) -> ModelSnapshot:
        return self  # immutable (the shapes are frozen): Drake copies abstract state values often

    def margin_mm(self, margins: UncertaintyMargins) -> float:
        """The uncertainty margin (mm) the filter adds to d_safe for this model (none for
        the prior, which is conservative by construction)."""
        return margins.margin_mm(None if self.shape is None else self.kind, self.residual_mm)


_PRIOR_AT_0 = ModelSnapshot("prior", None, 0.0, np.nan, 0)


def semi_axes_mm(shape) -> np.ndarray:
    """The semi-axes (mm) of a Sphere (its radius, once) or an Ellipsoid."""
    return np.atleast_1d(getattr(shape, "radii", getattr(shape, "radius", np.nan)))


def snapshot_of(model: AdaptiveEyeModel, coverage: DirectionCoverage, t_s: float, min_points: int = 0,
                min_scan_range_mm: float = 0.0, radius_range_mm: tuple = (0.0, np.inf)) -> ModelSnapshot:
    """The snapshot of `model` at t_s: its current shape once it rests on at least
    `min_points` points over `min_scan_range_mm` with semi-axes within `radius_range_mm`;
    an ellipsoid outside that range (a fit to a pathological eye, like the pointed eye's
    153 x 29 x 29 mm) gives way to the model's sphere fit if that one is an eye's (its
    phase's wider margin applies); "prior" otherwise. The model's shapes are made once
    per update (AdaptiveEyeModel.shape), and only once the trust limits on points and
    scan range are met; the coverage view is rebuilt only as DirectionCoverage.view says."""
    n = model.n_points
    shape = None if n < min_points or model.scan_range_mm < min_scan_range_mm else model.shape
    if shape is not None:
        last, (lo, hi) = model.history[-1], radius_range_mm
        if model.kind == "ellipsoid":
            radii = shape.radii.tolist()
            if lo <= min(radii) and max(radii) <= hi:
                return ModelSnapshot("ellipsoid", shape, t_s, float(last.ef_residual_mm), n, coverage.view(shape))
            shape = model.sphere  # the ellipsoid is no eye's: its sphere fit, if that one is
        if shape is not None and lo <= shape.radius <= hi:
            return ModelSnapshot("sphere", shape, t_s, float(last.sf_residual_mm), n, coverage.view(shape))
    return ModelSnapshot("prior", None, t_s, float("nan"), n, coverage.view())


class AdaptiveModelSystem(LeafSystem):
    """Feeds each packet of sensor samples (input "packet", a planning.iioct_sensor
    SensorPacket, its samples in time order as IioctSensorSystem delivers them) to an
    AdaptiveEyeModel: one update per packet with the valid points of its samples not
    seen before; state and output "snapshot" (ModelSnapshot). Runs at the packet rate,
    just after each packet is complete. Logs the distances and model updates when a
    logger is set."""

    def __init__(self, packet_rate_hz: float, offset_s: float, min_points: int, min_scan_range_mm: float,
                 radius_range_mm: tuple):
        super().__init__()
        self._trust = (min_points, min_scan_range_mm, radius_range_mm)
        self._packet = self.DeclareAbstractInputPort("packet", AbstractValue.Make(NO_SAMPLE_YET))
        self._snap = self.DeclareAbstractState(AbstractValue.Make(_PRIOR_AT_0))
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / packet_rate_hz, offset_s, self._update)
        self.DeclareStateOutputPort("snapshot", self._snap)
        self._compile()
        self.reset(AdaptiveEyeModel(), DirectionCoverage(np.zeros(3)))

    def _compile(self) -> None:
        """Compile (or load from numba's cache, ~0.5 s) the model's kernels before any run, so
        that no run's first packet holds it: a throwaway model with the predictive criteria
        (their checkpoints' kernels too) and its coverage take packets of 10 points from an
        eye-sized ellipsoid cap (mm) until both fits and a checkpoint's convergence test
        have run, then the snapshot of each kind (trust limits of 0: any shape)."""
        rng = np.random.default_rng(0)
        u = rng.normal(size=(300, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u[:, 2] = -np.abs(u[:, 2])  # a posterior cap
        P = u * [11.5, 11.4, 10.1] + rng.normal(0.0, 0.02, (300, 1)) * u
        model, coverage = AdaptiveEyeModel(criteria=PredictiveCriteria()), DirectionCoverage(np.zeros(3))
        for k in range(0, len(P), 10):
            model.update(P[k:k + 10])
            coverage.add(model.last_accepted)
        for shape in (None, model.sphere, model.ellipsoid):
            coverage.view(shape)
        snapshot_of(model, coverage, 0.0)

    def reset(self, model: AdaptiveEyeModel, coverage: DirectionCoverage, logger=None) -> None:
        self.model, self.coverage, self.logger = model, coverage, logger
        self._last_t = -np.inf
        self._written = _PRIOR_AT_0  # the declared state's value, until initial_snapshot
        self.wall_s = 0.0  # wall time (s) of its updates since the reset
        self.update_us: list[float] = []
        self._distances: list[tuple] = []  # per packet: its extracted and true distances, and which are valid
        self.n_samples = 0
        self.n_invalid = 0
        self.epochs: list[ModelSnapshot] = []  # the snapshot whenever the filter's model changed kind

    @property
    def errors_mm(self) -> list[float]:
        """Extracted - true distance (mm) of the valid samples since the reset, in time order
        (evaluation; made when read from the packets' arrays, which no one changes)."""
        return [e for d, true, valid in self._distances for e in (d - true)[valid].tolist()]

    def _mark_epoch(self, snap: ModelSnapshot) -> None:
        if not self.epochs or self.epochs[-1].kind != snap.kind:
            self.epochs.append(snap)

    def snapshot_for(self, model: AdaptiveEyeModel, coverage: DirectionCoverage, t_s: float) -> ModelSnapshot:
        """What the filter would read of `model` at t_s under this loop's trust rules."""
        return snapshot_of(model, coverage, t_s, *self._trust)

    def initial_snapshot(self) -> ModelSnapshot:
        """The snapshot the run starts from (ClosedLoop.run puts it in the context's state)."""
        self._written = self.snapshot_for(self.model, self.coverage, 0.0)
        self._mark_epoch(self._written)
        return self._written

    def _update(self, context, state) -> None:
        t0 = time.perf_counter()
        self._absorb(context, state)
        self.wall_s += time.perf_counter() - t0

    def _absorb(self, context, state) -> None:
        packet = self._packet.Eval(context)
        if not packet.t_s.item(0) > self._last_t:  # samples seen before (or the placeholder before the first packet)
            new = np.flatnonzero(packet.t_s > self._last_t)  # in time order: the packet's last ones
            if not len(new):
                return
            packet = packet.take(new)
        T, valid = packet.t_s, packet.valid
        self._last_t = T.item(-1)
        first = self.n_samples
        self.n_samples += len(T)
        n_valid = valid.tolist().count(True)  # C calls only (np.count_nonzero is a Python function)
        self.n_invalid += len(T) - n_valid
        self._distances.append((packet.distance_mm, packet.true_distance_mm, valid))
        if self.logger is not None:
            ascans = packet.ascans
            for k, (t, d, ok, c) in enumerate(zip(T.tolist(), packet.distance_mm.tolist(), valid.tolist(),
                                                  packet.confidence.tolist())):
                self.logger.log_distance(t, d, ok, c)
                if ascans is not None and ascans[k] is not None and (first + k) % ASCAN_LOG_EVERY == 0:
                    self.logger.log_ascan(t, ascans[k], ok, packet.reasons[k])
        entry = None
        if n_valid:
            t0 = time.perf_counter()
            entry = self.model.update(packet.p_W if n_valid == len(T) else packet.p_W[valid])
            # only what the model took in: a floater the gate turned away must not count as
            # retina measured deep inside the model (it would become every nearby point's margin)
            self.coverage.add(self.model.last_accepted)
            self.update_us.append(1e6 * (time.perf_counter() - t0) / n_valid)
            if entry is not None and self.logger is not None:
                self.logger.log_model_update(self._last_t, entry)
        # the state is what this system last wrote (or the initial snapshot): kept at hand
        if entry is not None or self._written.shape is None:
            self._written = snapshot_of(self.model, self.coverage, self._last_t, *self._trust)
        else:
            self._written = self._written._replace(t_s=self._last_t)
        state.get_mutable_abstract_state(0).set_value(self._written)
        self._mark_epoch(self._written)


class Step(NamedTuple):
    """One control step's record: time, joints, command and result, what the filter saw
    (mm, s, rad; W). The tip velocity done is J_tip qdot (LoopRun computes it)."""

    t: float
    q: np.ndarray
    qdot: np.ndarray
    v_cmd: np.ndarray
    J_tip: np.ndarray
    ok: bool
    reason: str
    intervened: bool
    solve_us: float
    step_us: float
    model_clearance: float
    kind: str
    rcm_error_mm: float
    points_W: np.ndarray
    lens_W: np.ndarray


@dataclass
class StepRecord:
    """A run's steps (one Step each: one append per control step) and the (q, v_cmd) on
    which Drake's diff IK is timed after the run."""

    steps: list = field(default_factory=list)
    drake_diffik_us: list = field(default_factory=list)
    diffik_states: list = field(default_factory=list)


class FilterSystem(LeafSystem):
    """The safety filter at the control rate: inputs "q", "snapshot" (the model, and through
    its time the sensor's freshness: sensor -> model -> filter), "measurement" (the
    sensor's latest [distance, valid, confidence, t_s], read for the log's beam only);
    state and output "qdot" (zero-order hold; the integrator, updating at the same instants,
    applies a step's qdot from the next step on: one control period of actuation latency,
    the same at every step). Each step asks the command source (`source`, set by
    `reset`: eval.commands' signature) for the tip velocity and roll rate at the joint
    angles it filters, then runs as one compiled call (eval.control_step); a fault or an
    unusual step goes to the reference, SafetyFilter on `inputs`, which the log records
    and `vitreoguard replay` re-runs."""

    def __init__(self, robot: Robot, config: LoopConfig, prior):
        super().__init__()
        self.robot, self.config, self.prior = robot, config, prior
        self.filter = SafetyFilter(config.filter)
        self.compiled = CompiledStep(robot, config, prior, self.filter)
        self.drake_diffik = DrakeDiffIK(robot, config.control_rate_hz)
        self.lens = robot.scenario.lens_W
        chain = robot.chain
        self._tip_chain = (chain.S, *chain.homes["T"])  # frame_position's (S, R_home, p_home) of the tip T, without q
        self._q = self.DeclareVectorInputPort("q", 6)
        self._snap = self.DeclareAbstractInputPort("snapshot", AbstractValue.Make(ModelSnapshot("prior", None, 0.0, np.nan, 0)))
        self._meas = self.DeclareVectorInputPort("measurement", 4)
        state = self.DeclareDiscreteState(6)
        dt = 1.0 / config.control_rate_hz
        # the first step waits for the sensor's first packet (the robot holds still until then)
        first_s = dt * np.ceil(config.sensor_packet / config.sensor_rate_hz / dt + 0.5)
        # on the integrator's own series of times (period dt, offset 0), so that a step and
        # the integrator's update are one simulator step, always: a series offset to the
        # first step rounds apart from it (one step in four, each then a simulator step of
        # its own, whose filter saw the joint angles after that update instead of before)
        self._skip_before_s = first_s - 0.5 * dt
        self.DeclarePeriodicDiscreteUpdateEvent(dt, 0.0, self._update)
        self.DeclareStateOutputPort("qdot", state)
        self.reset(None, None)
        self._compile()

    def _compile(self) -> None:
        """Compile (or load from numba's cache) every kernel of the step before any run, so
        that no run's wall time holds a compilation: a step that holds the equality
        optimum, one that needs DAQP, then the same with its remembered active set."""
        scenario = self.robot.scenario
        prior, q = ModelSnapshot("prior", None, 0.0, np.nan, 0), start_posture(self.robot, scenario.eye_pose.p_WE, self.robot.p_WC)
        for v in (0.0, 60.0, 60.0):
            self.compiled.step(0.0, q, np.array([v, 0.0, 0.0, 0.0]), prior, 0.0)
        self.reset(None, None)

    def reset(self, source, logger=None) -> None:
        """A new run: the command source (called source(t_s, p_WT, q) -> (v_W (3,) mm/s,
        roll rad/s) once per step, in time order) and the run's logger (or None)."""
        self.source, self.logger, self.record = source, logger, StepRecord()
        self.wall_s = 0.0  # wall time (s) of its steps since the reset (command source, records and log included)
        self.command_wall_s = 0.0  # of which in the command source
        self.compiled.reset()

    def inputs(self, t_s: float, q, command, snap: ModelSnapshot, sensor_t_s: float):
        """(FilterInputs, InstrumentPoints) of one step; ValueError on bad joint angles."""
        robot = self.robot
        ip = instrument_points(robot, q, robot.p_WC, self.config.points)
        model, kind = (self.prior, None) if snap.shape is None else (snap.shape, snap.kind)
        # the prior lies inside every retina, so the shaft behind the tip (which crosses the
        # eye wall at the trocar) is outside it: against the prior only tip and port count
        k = 2 if kind is None else len(ip.names)
        trusted, misfit = np.ones(k, dtype=bool), np.zeros(k)
        if kind is not None and snap.coverage is not None:
            # the prior as fallback only for tip and port: the shaft points lie outside it by
            # construction (the prior phase's reason above), where it would only push them in
            trusted[:2] = snap.coverage.angle_from_data_rad(ip.P_W[:2]) <= np.radians(self.config.trust_angle_deg)
            misfit = snap.coverage.local_misfit_mm(ip.P_W[:k], np.radians(self.config.misfit_angle_deg))
        x = FilterInputs(
            t_s=t_s, q=np.array(q), q_min=robot.q_lower, q_max=robot.q_upper, qdot_max=robot.qdot_max,
            v_cmd_W=np.array(command[:3]), J_tip=ip.J_tip,
            boundary_points=[PointKinematics(n, p, J, bool(tr), float(m))
                             for n, p, J, tr, m in zip(ip.names[:k], ip.P_W[:k], ip.J_W[:k], trusted, misfit)],
            model=model, model_time_s=t_s if kind is None else snap.t_s, sensor_time_s=sensor_t_s,
            rcm_A=ip.rcm_A, rcm_b=ip.rcm_b, lens=self.lens,
            lens_points=[PointKinematics(n, p, J) for n, p, J in zip(ip.lens_names, ip.L_W, ip.J_L)],
            margin_mm=snap.margin_mm(self.config.margins), J_roll=ip.J_roll,
            roll_rate_cmd=float(command[3]), fallback=None if kind is None else self.prior,
        )
        return x, ip

    def _update(self, context, discrete_state) -> None:
        if context.get_time() < self._skip_before_s:  # before the first packet: qdot stays 0
            return
        t0 = time.perf_counter()
        self._step(context, discrete_state, t0)
        self.wall_s += time.perf_counter() - t0

    def _command(self, t_s: float, q: np.ndarray) -> np.ndarray:
        """The source's command (4,) [v_W (3,) mm/s, roll rad/s] at t_s for the joint angles
        q (6,) rad: the tip position from the robot's kinematic chain, compiled, without
        Robot.pose's argument checks (non-finite q gives a NaN tip, and the filter refuses
        the step)."""
        t0 = time.perf_counter()
        S, R_home, p_home = self._tip_chain
        v, roll = self.source(t_s, frame_position(S, q, R_home, p_home), q)
        command = np.empty(4)
        command[:3], command[3] = v, roll  # ValueError unless v holds 3 numbers
        self.command_wall_s += time.perf_counter() - t0
        return command

    def _step(self, context, discrete_state, t0: float) -> None:
        t = context.get_time()
        q = self._q.Eval(context)
        command = self._command(t, q)
        snap = self._snap.Eval(context)
        sensor_t = snap.t_s  # the newest sensor sample, relayed by the model system (ModelSnapshot.t_s)
        rec = self.record
        out, r = self.compiled.step(t, q, command, snap, sensor_t)
        if out is not None:  # the ordinary step, compiled: the points from its kinematics
            k, m, P = r.k, r.m, r.P_W
            J_tip, P_W, L_W, rcm_error_mm = r.J_tip, P[:k], P[k:k + m], float(r.rcm_error_mm)
            x = self.inputs(t, q, command, snap, sensor_t)[0] if self.logger is not None else None
        else:  # a fault or an unusual step: the reference filter decides and says why
            try:
                x, ip = self.inputs(t, q, command, snap, sensor_t)
            except ValueError as exc:  # non-finite joint angles: nothing to filter, stay put
                rec.steps.append(Step(t, q, np.zeros(6), command[:3], np.zeros((3, 6)), False, f"bad joint state: {exc}",
                                      True, 0.0, 0.0, np.nan, snap.kind, np.nan, np.full((1, 3), np.nan),
                                      np.zeros((0, 3))))
                discrete_state.set_value(np.zeros(6))
                return
            out = self.filter(x)
            J_tip, P_W, L_W, rcm_error_mm = ip.J_tip, ip.P_W, ip.L_W, ip.rcm_error_mm
        discrete_state.set_value(out.qdot)
        step_us = 1e6 * (time.perf_counter() - t0)
        if self.config.drake_diffik_every and len(rec.steps) % self.config.drake_diffik_every == 0 and out.ok:
            rec.diffik_states.append((q, command[:3]))  # Drake is timed on these after the run (ClosedLoop.run)
        rec.steps.append(Step(t, q, out.qdot, command[:3], J_tip, out.ok, out.reason, out.intervened, out.solve_us,
                              step_us, out.min_clearance_mm, snap.kind, rcm_error_mm, P_W, L_W))
        if self.logger is not None:
            meas = self._meas.Eval(context)
            self._log(t, q, x, out, float(meas[0]) if meas[1] > 0 else float("nan"))

    def time_drake_diffik(self) -> None:
        """Time Drake's DoDifferentialInverseKinematics on the states recorded during the
        run (every drake_diffik_every-th step the filter solved), into the record: the
        same plant and states as the filter, outside the run's wall time (it is the
        comparison, not part of the loop)."""
        rec = self.record
        for q, v_cmd in rec.diffik_states:
            t1 = time.perf_counter()
            self.drake_diffik(q, v_cmd)
            rec.drake_diffik_us.append(1e6 * (time.perf_counter() - t1))

    def _log(self, t: float, q, x, out, distance_mm: float) -> None:
        """Every step's filter inputs and outputs; joint states at 100 Hz; frames and the
        3D scene (model, lens, trocar, the beam to the last measured distance) at 20 Hz."""
        log, k = self.logger, len(self.record.steps)
        log.log_filter_step(x, out)
        if k % 10 == 1:
            log.log_joint_states(t, q, out.qdot, JOINT_NAMES)
        if k % 50 == 1:
            frames = {}
            for name in ("F", "T", "S", "P"):
                R, p = self.robot.pose(name, q)
                X = np.eye(4)
                X[:3, :3], X[:3, 3] = R, p
                frames[name] = X
            log.log_frames(t, frames)
            o, u = self.robot.beam(q)
            beam = None if not np.isfinite(distance_mm) else (o, o + distance_mm * u)
            log.log_scene(t, eye=x.model, beam=beam, p_W_trocar=self.robot.p_WC, lens=self.lens)


@dataclass(frozen=True, eq=False)
class LoopRun:
    """One closed-loop run (arrays over control steps; mm, s, rad).

    `true_clearance_mm` (M,): the smallest TRUE clearance of the monitored points per
    step (ground-truth eye); `lens_clearance_mm` (M,): the shaft's lens points' smallest
    distance outside the lens keep-out; `wall_s` the run's wall time, of which
    `command_wall_s` in the command source (its tip position included), `model_wall_s`
    in the model system (its sensor packets' hand-over, model updates and snapshots) and
    `filter_wall_s` in the rest of the filter system's steps (the filter, its record and
    log); `model_epochs` the
    model the filter used (ModelSnapshot, W) from each change of kind on (prior -> sphere
    -> ellipsoid), the first one from the start of the run."""

    t: np.ndarray
    q: np.ndarray
    qdot: np.ndarray
    v_cmd: np.ndarray
    v_tip: np.ndarray
    ok: np.ndarray
    reasons: list
    intervened: np.ndarray
    solve_us: np.ndarray
    step_us: np.ndarray
    model_clearance_mm: np.ndarray
    true_clearance_mm: np.ndarray
    lens_clearance_mm: np.ndarray
    kind: list
    rcm_error_mm: np.ndarray
    drake_diffik_us: np.ndarray
    model_update_us: np.ndarray
    wall_s: float
    model_epochs: list = field(default_factory=list)
    command_wall_s: float = 0.0
    model_wall_s: float = 0.0
    filter_wall_s: float = 0.0
    logged: bool = False  # every step went to an MCAP log (RunLogger): JSON per step, ~1 x real time

    @property
    def duration_s(self) -> float:
        return float(len(self.t)) * float(self.t[1] - self.t[0]) if len(self.t) > 1 else 0.0

    @property
    def realtime_factor(self) -> float:
        return self.duration_s / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def failsafe_stops(self) -> int:
        """Steps the filter refused to move (a fault), counted as runs of consecutive steps."""
        bad = ~self.ok
        return int(np.sum(bad[1:] & ~bad[:-1]) + (bad[0] if len(bad) else 0))

    def free_tracking_error(self) -> np.ndarray:
        """|v_tip - v_cmd| / |v_cmd| on the steps where the filter did not intervene."""
        free = self.ok & ~self.intervened
        speed = np.linalg.norm(self.v_cmd[free], axis=1)
        err = np.linalg.norm(self.v_tip[free] - self.v_cmd[free], axis=1)
        return err[speed > 0] / speed[speed > 0]


def true_clearances(points_W: list, true_eye) -> np.ndarray:
    """(M,) the smallest true clearance (mm, > 0 inside) of each step's points (k_i, 3)."""
    counts = np.array([len(p) for p in points_W])
    d = np.asarray(true_eye.signed_distance(np.vstack(points_W)), dtype=float)
    return np.minimum.reduceat(d, np.concatenate([[0], np.cumsum(counts)[:-1]]))


class ClosedLoop:
    """The diagram on one scenario (planning.SurgeryScenario); `run` simulates it.
    `floater_rate`: fraction of iiOCT samples with a vitreous floater (IioctSensor)."""

    def __init__(self, scenario, config: LoopConfig = LoopConfig(), sensor_seed: int = 0, floater_rate: float = 0.0):
        self.scenario, self.config = scenario, config
        self.robot = Robot(scenario)
        self.prior = conservative_prior(scenario.eye_pose.p_WE)
        builder = DiagramBuilder()
        self.filter = builder.AddSystem(FilterSystem(self.robot, config, self.prior))
        self.integrator = builder.AddSystem(DiscreteTimeIntegrator(6, 1.0 / config.control_rate_hz))
        self.sensor = IioctSensor(Robot(scenario), mode=config.sensor_mode, floater_rate=floater_rate, seed=sensor_seed)
        # q is the integrator's zero-order hold at the control rate: the sensor latches it at that rate
        sensor_sys = builder.AddSystem(IioctSensorSystem(self.sensor, config.sensor_rate_hz, packet=config.sensor_packet,
                                                         input_rate_hz=config.control_rate_hz))
        packet_s = config.sensor_packet / config.sensor_rate_hz
        # the model reads each packet a quarter sample period after the sensor has made it
        self.model = builder.AddSystem(AdaptiveModelSystem(1.0 / packet_s,
                                                           sensor_sys.packet_offset_s + 0.25 / config.sensor_rate_hz,
                                                           config.model_min_points, config.model_min_scan_range_mm,
                                                           config.model_radius_range_mm))
        q = self.integrator.get_output_port()
        for port in (self.filter.GetInputPort("q"), sensor_sys.GetInputPort("q")):
            builder.Connect(q, port)
        builder.Connect(self.filter.GetOutputPort("qdot"), self.integrator.get_input_port())
        builder.Connect(sensor_sys.GetOutputPort("packet"), self.model.GetInputPort("packet"))
        builder.Connect(sensor_sys.GetOutputPort("measurement"), self.filter.GetInputPort("measurement"))
        builder.Connect(self.model.GetOutputPort("snapshot"), self.filter.GetInputPort("snapshot"))
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)

    def run(self, source, q0, duration_s: float, model: AdaptiveEyeModel | None = None,
            coverage: DirectionCoverage | None = None, logger=None) -> LoopRun:
        """Simulate `duration_s` s from joint angles q0 (6,) rad under the command `source`
        (eval.commands), continuing `model` and its `coverage` (fresh ones if None; both
        updated in place). Logs to `logger` (eval.mcap_log.RunLogger) when given."""
        q0 = np.asarray(q0, dtype=float)
        if q0.shape != (6,) or not np.all(np.isfinite(q0)):
            raise ValueError(f"q0 must be 6 finite joint angles (rad), got {q0}")
        if not (np.isfinite(duration_s) and duration_s > 0):
            raise ValueError(f"duration_s must be > 0 s, got {duration_s}")
        self.filter.reset(source, logger)
        self.model.reset(AdaptiveEyeModel() if model is None else model,
                         self.new_coverage() if coverage is None else coverage, logger)
        context = self.diagram.CreateDefaultContext()
        self.integrator.set_integral_value(self.integrator.GetMyMutableContextFromRoot(context), q0)
        self.model.GetMyMutableContextFromRoot(context).get_mutable_abstract_state(0).set_value(
            self.model.initial_snapshot())
        self.simulator.reset_context(context)
        self.simulator.Initialize()
        # the objects alive before the run (the model's history: tens of thousands) are left
        # out of the garbage collector's passes during it; a full pass over them took 0.24 s
        # of a 3.5 s spiral. Objects made during the run are collected as usual.
        gc.freeze()
        try:
            t0 = time.perf_counter()
            self.simulator.AdvanceTo(duration_s)
            wall = time.perf_counter() - t0
        finally:
            gc.unfreeze()
        self.filter.time_drake_diffik()
        return self._collect(wall, logger is not None)

    def new_coverage(self) -> DirectionCoverage:
        """An empty record of measured directions, seen from the nominal eye centre."""
        return DirectionCoverage(self.scenario.eye_pose.p_WE)

    def _collect(self, wall_s: float, logged: bool) -> LoopRun:
        steps = self.filter.record.steps
        eye, lens = self.scenario.eye, self.scenario.lens_W
        col = {name: [getattr(st, name) for st in steps] for name in Step._fields}
        lens_pts = [p for p in col["lens_W"] if len(p)]
        lens_counts = np.array([len(p) for p in col["lens_W"]])
        lens_clear = np.full(len(steps), np.inf)
        if lens_pts:
            d = -np.asarray(lens.signed_distance(np.vstack(lens_pts)))
            starts = np.concatenate([[0], np.cumsum(lens_counts[lens_counts > 0])[:-1]])
            lens_clear[lens_counts > 0] = np.minimum.reduceat(d, starts)
        a = lambda x, shape=None: np.array(x, dtype=float) if len(x) else np.zeros(shape or (0,))  # noqa: E731
        qdot, J_tip = a(col["qdot"], (0, 6)), a(col["J_tip"], (0, 3, 6))
        return LoopRun(
            t=a(col["t"]), q=a(col["q"], (0, 6)), qdot=qdot, v_cmd=a(col["v_cmd"], (0, 3)),
            v_tip=np.einsum("kij,kj->ki", J_tip, qdot), ok=np.array(col["ok"], dtype=bool), reasons=col["reason"],
            intervened=np.array(col["intervened"], dtype=bool), solve_us=a(col["solve_us"]), step_us=a(col["step_us"]),
            model_clearance_mm=a(col["model_clearance"]),
            true_clearance_mm=true_clearances(col["points_W"], eye) if steps else np.zeros(0),
            lens_clearance_mm=lens_clear, kind=col["kind"], rcm_error_mm=a(col["rcm_error_mm"]),
            drake_diffik_us=a(self.filter.record.drake_diffik_us), model_update_us=a(self.model.update_us), wall_s=wall_s,
            model_epochs=list(self.model.epochs), command_wall_s=self.filter.command_wall_s, model_wall_s=self.model.wall_s,
            filter_wall_s=self.filter.wall_s - self.filter.command_wall_s,
            logged=logged,
        )
