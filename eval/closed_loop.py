"""The closed loop as a Drake diagram: command -> safety filter -> integrator -> sensor -> model.

    FilterSystem (1 kHz: calls the command source on the joint angles it filters, then
        filters the command; zero-order hold of qdot)
        --qdot--> [ActuatorSystem: delay, lag, acceleration limits, when not ideal;
                   its state back to the filter]
        --qdot--> DiscreteTimeIntegrator (q_{k+1} = q_k + dt qdot_k) --q--> everything
    q --> IioctSensorSystem (2 kHz: beam from the TRUE sensor pose on the TRUE eye; point
          from the reported angles and the CALIBRATED sensor pose; q latched at the
          control rate, at which the integrator's q changes)
      --packet--> AdaptiveModelSystem (updates the AdaptiveEyeModel with each packet's
          valid points) --snapshot--> FilterSystem

The systems live in eval.systems. The filter's inputs and outputs of every step go to
the run's MCAP log (RunLogger) so that `vitreoguard replay` re-runs them, and every
step's monitored points are kept so that their TRUE clearance is evaluated afterwards,
vectorised (LoopRun). The systems hold Python objects that change during a simulation
(the model, the command source, the records): one simulation at a time per ClosedLoop,
reset by `run`. Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import gc
import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus
from pydrake.systems.primitives import DiscreteTimeIntegrator

from eval.clearance import bound_excess, true_clearances
from eval.loop_config import LoopConfig
from eval.systems.actuator import ActuatorSystem
from eval.systems.filter import FilterSystem
from eval.systems.step_record import Step
from eval.systems.model import AdaptiveModelSystem, ModelSnapshot, semi_axes_mm, snapshot_of
from eval.systems.sensor import IioctSensorSystem
from models import AdaptiveEyeModel
from models.adaptive.coverage import DirectionCoverage
from models.adaptive.transition import PredictiveCriteria
from models.local.grid import LocalRetinaModel
from planning.iioct import IioctSensor
from planning.robot import Robot
from safety.margins import conservative_prior

__all__ = ["ClosedLoop", "LoopConfig", "LoopRun", "ModelSnapshot", "semi_axes_mm", "snapshot_of", "true_clearances"]


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
    -> ellipsoid), the first one from the start of the run. `bound_excess_mm`: the largest
    amount by which the bound on a monitored point's true clearance that the barrier
    assumed (h - k sigma - calibration) exceeded its true clearance, at step
    `bound_excess_step`, where that point's true clearance was `bound_excess_clearance_mm`
    (eval.clearance.bound_excess; > 0: the rule's premise failed there; -inf: no bound);
    `bound_excess_in_reach_mm` the same over the bounds within the barrier's reach of
    d_safe (d_safe + max tip speed / gain: the rows that can act within the step)."""

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
    logged: bool = False  # every step went to an MCAP log (RunLogger): slower than an unlogged run
    bound_excess_mm: float = -np.inf
    bound_excess_step: int = -1
    bound_excess_clearance_mm: float = np.nan
    bound_excess_in_reach_mm: float = -np.inf
    filter_replay_us: np.ndarray = field(default_factory=lambda: np.zeros(0))  # FilterSystem.time_references

    @property
    def duration_s(self) -> float:
        return float(len(self.t)) * float(self.t[1] - self.t[0]) if len(self.t) > 1 else 0.0

    @property
    def realtime_factor(self) -> float:
        return self.duration_s / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def failsafe_stops(self) -> int:
        """Steps at which the filter held the robot still (a fault), counted as runs of consecutive steps."""
        bad = ~self.ok
        return int(np.sum(bad[1:] & ~bad[:-1]) + (bad[0] if len(bad) else 0))

    def free_tracking_error(self) -> np.ndarray:
        """|v_tip - v_cmd| / |v_cmd| on the steps where the filter did not intervene."""
        free = self.ok & ~self.intervened
        speed = np.linalg.norm(self.v_cmd[free], axis=1)
        err = np.linalg.norm(self.v_tip[free] - self.v_cmd[free], axis=1)
        return err[speed > 0] / speed[speed > 0]


def _delayed(source, t0_s: float):
    """The command source called with the time since t0_s."""
    return lambda t_s, p_WT, q: source(t_s - t0_s, p_WT, q)


class ClosedLoop:
    """The diagram on one scenario (planning.SurgeryScenario); `run` simulates it.
    `floater_rate`: fraction of iiOCT samples with a vitreous floater (IioctSensor)."""

    def __init__(self, scenario, config: LoopConfig = LoopConfig(), sensor_seed: int = 0, floater_rate: float = 0.0):
        self.scenario, self.config = scenario, config
        self._construction = (scenario, config, sensor_seed, floater_rate)
        self.robot = Robot(scenario)
        self.prior = conservative_prior(scenario.eye_pose.p_WE)
        builder = DiagramBuilder()
        self.filter = builder.AddSystem(FilterSystem(self.robot, config, self.prior))
        self.integrator = builder.AddSystem(DiscreteTimeIntegrator(6, 1.0 / config.control_rate_hz))
        self.sensor = IioctSensor(Robot(scenario), mode=config.sensor_mode, floater_rate=floater_rate, seed=sensor_seed,
                                  encoder_noise_rad=config.encoder_noise_rad)
        # q is the integrator's zero-order hold at the control rate: the sensor latches it at that rate
        sensor_sys = builder.AddSystem(IioctSensorSystem(self.sensor, config.sensor_rate_hz, config.oct_time_offset_s,
                                                         packet=config.sensor_packet,
                                                         input_rate_hz=config.control_rate_hz,
                                                         stream_fault=config.stream_fault))
        packet_s = config.sensor_packet / config.sensor_rate_hz
        # the model reads each packet a quarter sample period after the sensor has made it
        self.model = builder.AddSystem(AdaptiveModelSystem(1.0 / packet_s,
                                                           sensor_sys.packet_offset_s + 0.25 / config.sensor_rate_hz,
                                                           config.model_min_points, config.model_min_scan_range_mm,
                                                           config.model_radius_range_mm,
                                                           field_bound=config.filter.field_bound(self.prior),
                                                           max_incidence_rad=self.sensor.max_incidence_rad))
        q = self.integrator.get_output_port()
        for port in (self.filter.GetInputPort("q"), sensor_sys.GetInputPort("q")):
            builder.Connect(q, port)
        if config.actuator.ideal:  # the filter's command over the next control period
            builder.Connect(self.filter.GetOutputPort("qdot"), self.integrator.get_input_port())
        else:  # command -> actuator (delay, lag, acceleration limit) -> joints; the filter reads its state
            actuator = builder.AddSystem(ActuatorSystem(config.actuator, 1.0 / config.control_rate_hz))
            builder.Connect(self.filter.GetOutputPort("qdot"), actuator.GetInputPort("qdot_cmd"))
            builder.Connect(actuator.GetOutputPort("qdot"), self.integrator.get_input_port())
            builder.Connect(actuator.GetOutputPort("state"), self.filter.GetInputPort("actuator"))
        builder.Connect(sensor_sys.GetOutputPort("packet"), self.model.GetInputPort("packet"))
        builder.Connect(sensor_sys.GetOutputPort("measurement"), self.filter.GetInputPort("measurement"))
        builder.Connect(self.model.GetOutputPort("snapshot"), self.filter.GetInputPort("snapshot"))
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)

    def __reduce__(self):
        """Pickled as its construction: a worker process builds its own diagram (the compiled
        kernels load from numba's cache)."""
        return (ClosedLoop, self._construction)

    def run(self, source, q0, duration_s: float, model: AdaptiveEyeModel | None = None,
            coverage: DirectionCoverage | None = None, logger=None, sensor_seed=None) -> LoopRun:
        """Simulate `duration_s` s from joint angles q0 (6,) rad under the command `source`
        (eval.experiments.command_sources) through the scenario's trocar, continuing `model`
        and its `coverage` (fresh ones if None; both updated in place). Logs to `logger`
        (eval.log.writer.RunLogger) when given. `sensor_seed` (an int or a numpy
        SeedSequence): the sensor's draws start from it (None: they go on from the previous
        run's)."""
        return self.run_segments([(self.robot.p_WC, source, q0, duration_s)], model, coverage, logger, sensor_seed)

    def run_segments(self, segments, model: AdaptiveEyeModel | None = None, coverage: DirectionCoverage | None = None,
                     logger=None, sensor_seed=None) -> LoopRun:
        """Simulate segments one after the other in one run, each (p_WC (3,) mm: its trocar,
        source, q0 (6,) rad, duration_s s): the filter's RCM and monitored points follow the
        segment's trocar (FilterSystem.set_trocar), the joints start it at q0 with the
        filter's held command zeroed (what happens between segments, a switch of ports
        outside the eye, is not simulated) and its source is called with the time since the
        segment's start. Simulation time runs on across segments. A source with a `finished`
        attribute (eval.experiments.command_sources.PacedTipPath) ends its segment at the
        first control step after it turns true, before its duration is out."""
        segments = [(np.asarray(p, dtype=float), src, np.asarray(q0, dtype=float), float(d)) for p, src, q0, d in segments]
        for _, _, q0, d in segments:
            if q0.shape != (6,) or not np.all(np.isfinite(q0)):
                raise ValueError(f"q0 must be 6 finite joint angles (rad), got {q0}")
            if not (np.isfinite(d) and d > 0):
                raise ValueError(f"duration_s must be > 0 s, got {d}")
        if sensor_seed is not None:
            self.sensor.reseed(sensor_seed)
        self.filter.reset(None, logger)
        self.model.reset(self.new_model() if model is None else model,
                         self.new_coverage() if coverage is None else coverage, logger)
        context = self.diagram.CreateDefaultContext()
        self.model.GetMyMutableContextFromRoot(context).get_mutable_abstract_state(0).set_value(
            self.model.initial_snapshot())
        self.simulator.reset_context(context)
        # the objects alive before the run (the model's history: tens of thousands) are left
        # out of the garbage collector's passes during it; a full pass over them took 0.24 s
        # of a 3.5 s spiral. Objects made during the run are collected as usual.
        gc.freeze()
        wall, t_end = 0.0, 0.0
        try:
            for k, (p_WC, source, q0, duration_s) in enumerate(segments):
                self.filter.set_trocar(p_WC)
                self.filter.source = source if k == 0 else _delayed(source, t_end)
                context = self.simulator.get_mutable_context()
                self.integrator.set_integral_value(self.integrator.GetMyMutableContextFromRoot(context), q0)
                if k:  # the segment starts at q0 at rest, not with the other segment's last command held
                    self.filter.GetMyMutableContextFromRoot(context).get_mutable_discrete_state(0).set_value(np.zeros(6))
                if k == 0:
                    self.simulator.Initialize()
                self._end_when_finished(source)
                t0 = time.perf_counter()
                self.simulator.AdvanceTo(t_end + duration_s)
                wall += time.perf_counter() - t0
                t_end = context.get_time()
        finally:
            self.simulator.clear_monitor()
            gc.unfreeze()
        self.model.flush_log()
        self.filter.time_references()
        return self._collect(wall, logger is not None)

    def _end_when_finished(self, source) -> None:
        """The simulator's monitor: the run's segment ends once `source.finished` (a source
        without one, or whose `finished` is None, runs its whole duration)."""
        if getattr(source, "finished", None) is None:
            self.simulator.clear_monitor()
            return
        diagram = self.diagram

        def monitor(context):
            return EventStatus.ReachedTermination(diagram, "the command's path is done") if source.finished else None

        self.simulator.set_monitor(monitor)

    def new_model(self) -> AdaptiveEyeModel:
        """A fresh adaptive model with the predictive criteria and, with config.local_model,
        the local model about the nominal eye centre (models.local) and the trocar's pivot
        as a known point of the eye wall (models.fit.eye_globe)."""
        local = LocalRetinaModel(self.scenario.eye_pose.p_WE) if self.config.local_model else None
        return AdaptiveEyeModel(criteria=PredictiveCriteria(), local=local, wall_W=self.scenario.p_WC[None])

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
        f = self.config.filter
        (excess, at, clearance), (in_reach, _, _) = bound_excess(
            col["points_W"], col["bounds_mm"], eye, (np.inf, f.d_safe_mm + f.barrier_reach_mm))
        return LoopRun(
            t=a(col["t"]), q=a(col["q"], (0, 6)), qdot=qdot, v_cmd=a(col["v_cmd"], (0, 3)),
            v_tip=np.einsum("kij,kj->ki", J_tip, qdot), ok=np.array(col["ok"], dtype=bool), reasons=col["reason"],
            intervened=np.array(col["intervened"], dtype=bool), solve_us=a(col["solve_us"]), step_us=a(col["step_us"]),
            model_clearance_mm=a(col["model_clearance"]),
            true_clearance_mm=true_clearances(col["points_W"], eye) if steps else np.zeros(0),
            lens_clearance_mm=lens_clear, kind=col["kind"], rcm_error_mm=a(col["rcm_error_mm"]),
            drake_diffik_us=a(self.filter.record.drake_diffik_us),
            filter_replay_us=a(self.filter.record.filter_replay_us), model_update_us=a(self.model.update_us), wall_s=wall_s,
            model_epochs=list(self.model.epochs), command_wall_s=self.filter.command_wall_s, model_wall_s=self.model.wall_s,
            filter_wall_s=self.filter.wall_s - self.filter.command_wall_s,
            logged=logged, bound_excess_mm=excess, bound_excess_step=at, bound_excess_clearance_mm=clearance,
            bound_excess_in_reach_mm=in_reach,
        )
