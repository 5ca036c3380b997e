"""The safety filter as a Drake system at the control rate.

Each step asks the command source for the tip velocity and roll rate at the joint
angles it filters, then runs the filter's compiled step (safety.ConstraintStack built
from the loop's constraints, with the instrument's kinematics kernel): the points, the
eye model as a distance field (with the local model, models.local.field: its surface and
standard deviation, the boundary d_safe + k sigma; else models.adaptive.model_field: the
model's shape, its phase margin, the misfit measured near each point, and the prior where
the model has no data near the tip or the port), the lens, the RCM and the joint limits, in one call. A fault
gives zero velocity and the reason from the same call.

The shaft points count only against a fitted model: the prior lies inside every retina,
and the shaft crosses the eye wall at the trocar, so the shaft behind the tip lies
outside the prior by construction. The quadric's field puts the prior in place of the
model where the model has no data: the shaft keeps to the model alone. The local model's
barrier takes the larger of two bounds on the true clearance, the model's h - k sigma and
the prior's: the shaft keeps to it as the tip does (near the trocar the prior's bound is
negative and never the larger; near the eye's centre, where the model's first-order
distance falls far below the true one, it is). Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from eval.log.robot_scene import RobotScene, shrunk
from eval.log.steps import setup_to_json
from eval.loop_config import LoopConfig
from eval.systems.inputs import StepInputs
from eval.systems.model import ModelSnapshot
from eval.systems.step_record import Step, StepRecord
from models.adaptive.coverage import band_chord
from models.adaptive.model_field import ModelField, coverage_trust, model_field_kernel
from models.local.field import FieldValues, LocalField
from models.local.field_kernels import local_field
from planning.chain import frame_position
from planning.diffik import DrakeDiffIK
from planning.robot import RCM_GAIN_PER_S, Robot
from planning.scan import start_posture
from planning.step_kinematics import (GROUP_CAPACITY, POINT_GROUPS, point_names, step_kinematics,
                                      step_kinematics_params, step_pose)
from safety import ConstraintStack, default_constraints
from safety.filter import rcm_constraint
from safety.constraints import RcmEquality
from safety.constraints.actuated_barrier import actuator_aware

JOINT_NAMES = tuple(f"J{k}" for k in range(1, 7))


def loop_constraints(robot: Robot, config: LoopConfig) -> list:
    """The loop's constraint stack: tip speed, joint limits, the tip and port against the
    eye field (slot "eye"), the shaft against the fitted model (slot "eye_shaft"), the lens
    keep-out (slot "lens"), the RCM through the robot's trocar, then config.extra_constraints.
    With an actuator that is not ideal, the eye barriers are actuator-aware
    (safety.constraints.actuated_barrier: they read the actuator's pending displacements)."""
    out = default_constraints(config.filter, robot.q_lower, robot.q_upper, robot.qdot_max,
                              (("tip_port", "eye", 2), ("shaft", "eye_shaft", 0)), ("lens", "lens"),
                              rcm_constraint(config.filter, robot.p_WC, RCM_GAIN_PER_S),
                              config.extra_constraints)
    return out if config.actuator.ideal else actuator_aware(out)


class FilterSystem(LeafSystem):
    """The safety filter at the control rate: inputs "q", "snapshot" (the model, and through
    its time the sensor's freshness), "measurement" (the sensor's latest [distance, valid,
    confidence, t_s], read for the log's beam only); state and output "qdot" (zero-order
    hold; the integrator, updating at the same instants, applies a step's qdot from the
    next step on: one control period of actuation latency, the same at every step). The
    command source (`source`, set by `reset`: eval.experiments.command_sources' signature) is called inside
    the step. With a logger, each step's FilterInputs (`inputs`) go to the log, which
    `vitreoguard replay` re-runs through safety.SafetyFilter."""

    def __init__(self, robot: Robot, config: LoopConfig, prior):
        super().__init__()
        self.robot, self.config, self.prior = robot, config, prior
        self.constraints = loop_constraints(robot, config)
        self.lens = robot.scenario.lens_W
        lens = self.lens.field_kernel()  # the keep-out ellipsoid's own distance field
        self.step_inputs = StepInputs(robot, config.points, config.filter, prior)
        self.robot_scene = RobotScene(robot)
        self.local = config.local_model
        eye_kernel, shaft_kernel = (local_field,) * 2 if self.local else (model_field_kernel,) * 2
        self.stack = ConstraintStack(self.constraints, {g: GROUP_CAPACITY[g] for g in POINT_GROUPS},
                                     {"eye": eye_kernel, "eye_shaft": shaft_kernel,
                                      "lens": lens.kernel}, config.filter, kinematics=(step_kinematics, step_pose),
                                     point_names=point_names, port=("tip_port", 1))
        self._rcm = next(c for c in self.constraints if isinstance(c, RcmEquality))
        self.p_WC = np.asarray(robot.p_WC, dtype=float)  # the active trocar (set_trocar)
        self._kp = step_kinematics_params(robot, self.p_WC, config.points)
        self.drake_diffik = DrakeDiffIK(robot, config.control_rate_hz)
        self._lens_field = lens.params
        self._prior_fields = ((LocalField.exact(prior, robot.scenario.eye_pose.p_WE), LocalField.none()) if self.local
                              else (ModelField(prior), ModelField.none()))  # before the model has a shape
        self._bounded = None  # the local field with the prior as its second bound (fields)
        chord = max(band_chord(np.radians(config.trust_angle_deg)), band_chord(np.radians(config.misfit_angle_deg)))
        self._field_options = dict(trust_angle_rad=float(np.radians(config.trust_angle_deg)),
                                   misfit_angle_rad=float(np.radians(config.misfit_angle_deg)), band_chord=chord)
        self._key, self._fields = None, ()
        self._times = np.zeros(3)  # [now, the model's time, the newest sensor sample's] s
        chain = robot.chain
        self._tip_chain = (chain.S, *chain.homes["T"])  # frame_position's (S, R_home, p_home) of the tip T, without q
        self._q = self.DeclareVectorInputPort("q", 6)
        self._snap = self.DeclareAbstractInputPort("snapshot", AbstractValue.Make(ModelSnapshot("prior", None, 0.0, np.nan, 0)))
        self._meas = self.DeclareVectorInputPort("measurement", 4)
        state = self.DeclareDiscreteState(6)
        dt = 1.0 / config.control_rate_hz
        self._dt = dt
        self._no_pending = np.zeros((0, 6))
        # the actuator's reported state: [applied velocity, queued commands] (eval.systems.actuator)
        self._actuator = None if config.actuator.ideal else self.DeclareVectorInputPort(
            "actuator", 6 * (1 + config.actuator.delay_steps(dt)))
        # the first step waits for the sensor's first packet (the robot holds still until then)
        first_s = dt * np.ceil(config.sensor_packet / config.sensor_rate_hz / dt + 0.5)
        # on the integrator's own series of times (period dt, offset 0), so that a step and
        # the integrator's update are one simulator step, always
        self._skip_before_s = first_s - 0.5 * dt
        self.DeclarePeriodicDiscreteUpdateEvent(dt, 0.0, self._update)
        self.DeclareStateOutputPort("qdot", state)
        self.reset(None, None)
        self._compile()

    def _compile(self) -> None:
        """Compile (or load from numba's cache) the step before any run, so that no run's wall
        time holds a compilation: a step that holds the equality optimum, one that needs
        DAQP, then the same with its remembered active set."""
        scenario = self.robot.scenario
        prior, q = ModelSnapshot("prior", None, 0.0, np.nan, 0), start_posture(self.robot, scenario.eye_pose.p_WE, self.robot.p_WC)
        for v in (0.0, 60.0, 60.0):
            self.filter_step(0.0, q, np.array([v, 0.0, 0.0, 0.0]), prior, 0.0)
        self.reset(None, None)

    def set_trocar(self, p_WC) -> None:
        """Make p_WC (3,) mm, W the active trocar: the RCM constraint and the monitored
        points (which shaft points lie past the trocar) follow it; the same compiled step
        with new numbers (ConstraintStack.set_params). A run's log gets the new setup."""
        p_WC = np.array(p_WC, dtype=float)
        if p_WC.shape != (3,) or not np.all(np.isfinite(p_WC)):
            raise ValueError(f"p_WC must be 3 finite mm, got {p_WC}")
        self._rcm = dataclasses.replace(self._rcm, p_WC=p_WC)
        self.constraints = [self._rcm if isinstance(c, RcmEquality) else c for c in self.constraints]
        self.stack.set_params(self.constraints)
        self.stack.reset()  # the last active set belongs to the other trocar's geometry
        self.p_WC, self._kp = p_WC, step_kinematics_params(self.robot, p_WC, self.config.points)
        self.step_inputs.set_trocar(p_WC)
        if self.logger is not None and not self.logger.closed:  # a run's log (not one of a finished run)
            self.logger.log_setup(self._setup())

    def _setup(self) -> dict:
        """The log's setup: the scenario with the active trocar, the monitored points, the trust rules."""
        scenario = self.robot.scenario
        if not np.allclose(self.p_WC, scenario.p_WC, atol=1e-9):
            scenario = dataclasses.replace(scenario, p_EC=scenario.eye_pose.to_E(self.p_WC[None])[0])
        return setup_to_json(scenario, self.config.points, self.config.trust_angle_deg, self.config.misfit_angle_deg)

    def reset(self, source, logger=None) -> None:
        """A new run: the command source (called source(t_s, p_WT, q) -> (v_W (3,) mm/s,
        roll rad/s) once per step, in time order) and the run's logger (or None)."""
        self.source, self.logger, self.record = source, logger, StepRecord()
        self._logged_state = (True, None)  # (ok, model kind) of the last logged step
        if logger is not None:
            logger.log_setup(self._setup())
        self.wall_s = 0.0  # wall time (s) of its steps since the reset (command source, records and log included)
        self.command_wall_s = 0.0  # of which in the command source
        self.stack.reset()

    def field_objects(self, snap: ModelSnapshot) -> tuple:
        """(eye, shaft) distance fields for a snapshot: what the tip and the port keep to (the
        model with the prior as a second bound) and what the watched shaft points keep to
        (the quadric's model alone; the local model's barrier, as the tip: module docstring);
        before the model has a shape, the prior and no bound. The quadric's is a
        models.adaptive.model_field.ModelField with the phase's margin; the local model's its
        models.local.field.LocalField (d_safe + sigma_factor x sigma), on the snapshot's own
        params when they hold the barrier's bound (the loop's model system writes it:
        AdaptiveModelSystem's field_bound)."""
        if self.local:
            if snap.field is None:
                return self._prior_fields
            barrier = snap.field.with_fallback(*self.config.filter.field_bound(self.prior))
            return barrier, barrier
        if snap.shape is None:
            return self._prior_fields
        field = ModelField(snap.shape, float(snap.margin_mm(self.config.margins)), snap.coverage, self.prior,
                           **self._field_options)
        return field, field.without_fallback()

    def fields(self, snap: ModelSnapshot) -> tuple:
        """The field slots' params ("eye", "eye_shaft", "lens") for a snapshot (field_objects):
        made once per model; a snapshot that differs from the last only in its time reuses them."""
        if self.local:
            if self._key is not snap.field or not self._fields:
                eye, shaft = self.field_objects(snap)
                self._bounded = None if snap.field is None else eye
                self._fields, self._key = (eye.params, shaft.params, self._lens_field), snap.field
            return self._fields
        key = (snap.shape, snap.coverage, snap.kind, snap.residual_mm)
        last = self._key
        if last is None or not (key[0] is last[0] and key[1] is last[1] and key[2] == last[2]
                                and (key[3] == last[3] or (key[3] != key[3] and last[3] != last[3]))):
            eye, shaft = self.field_objects(snap)
            self._fields, self._key = (eye.params, shaft.params, self._lens_field), key
        return self._fields

    def pending(self, context) -> np.ndarray:
        """(r, 6) rad: what the actuator still carries out if every command from this step on is
        zero (safety.actuator.ActuatorModel.pending_rows): its applied velocity, its queue
        and this filter's last command, which the actuator takes at this instant."""
        if self._actuator is None:
            return self._no_pending
        x = self._actuator.Eval(context)
        queued = np.empty((len(x) // 6, 6))
        queued[:-1] = x[6:].reshape(-1, 6)
        queued[-1] = context.get_discrete_state(0).get_value()
        return self.config.actuator.pending_rows(x[:6], queued, self._dt)

    def filter_step(self, t_s: float, q: np.ndarray, command: np.ndarray, snap: ModelSnapshot, sensor_t_s: float,
                    pending=None):
        """(FilterOutput, P (K, 3) mm, ranges, J_tip (3, 6) mm/rad, RCM error mm) of one step;
        `pending` the actuator's pending displacements (None: an ideal actuator)."""
        times = self._times
        times[0], times[1], times[2] = t_s, t_s if snap.shape is None else snap.t_s, sensor_t_s
        out, _, P, ranges, J_tip, rcm_error = self.stack.solve_at(q, command, times, self._kp, self.fields(snap),
                                                                  pending)
        return out, P, ranges, J_tip, rcm_error

    def inputs(self, t_s: float, q, command, snap: ModelSnapshot, sensor_t_s: float, pending=None):
        """(FilterInputs, InstrumentPoints) of one step, as replay rebuilds it from the log
        (`pending` the actuator's, None: ideal); ValueError on bad joint angles."""
        ip = self.step_inputs.points_at(q)
        shape, kind, margin, trusted, misfit = self._step_model(snap, ip.P_W)
        x = self.step_inputs(t_s, q, command, shape, kind, t_s if kind is None else snap.t_s, sensor_t_s, margin,
                             trusted, misfit, ip, pending)
        return x, ip

    def _step_model(self, snap: ModelSnapshot, P_W) -> tuple:
        """(shape, kind, margin mm, trusted flags, misfit mm) of a step whose monitored points
        (tip, port, shaft; planning.instrument_points) are P_W (K, 3) mm, as the log records
        them (StepInputs' arguments). With the local model: its field's answers
        at the boundary points (models.local.field.FieldValues) and their sigma as the points'
        margins (the barrier's k multiplies them), kind None before it is trusted."""
        if not self.local:
            kind = None if snap.shape is None else snap.kind
            return (snap.shape, kind, snap.margin_mm(self.config.margins),
                    *self._trust(snap, P_W[:StepInputs.boundary_count(kind, len(P_W))]))
        if snap.field is None:
            return None, None, 0.0, np.ones(2, dtype=bool), np.zeros(2)
        self.fields(snap)
        P = P_W[:StepInputs.boundary_count(snap.kind, len(P_W))]
        h, g, sigma = self._bounded.signed_distance_gradient_uncertainty(P)  # the shaft's points too
        return FieldValues(P, h, g), snap.kind, 0.0, np.ones(len(P), dtype=bool), sigma

    def _trust(self, snap: ModelSnapshot, P_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(trusted flags, measured misfit mm) of the boundary points P_W (k, 3) as the
        step's field decided them (models.adaptive.model_field.coverage_trust on the tip's
        and the port's field): the shaft's points are not subject to the trust rule."""
        trusted, misfit = coverage_trust(self.fields(snap)[0], np.ascontiguousarray(P_W, dtype=float))
        trusted[2:] = True
        return trusted, misfit

    def _update(self, context, discrete_state) -> None:
        if context.get_time() < self._skip_before_s:  # before the first packet: qdot stays 0
            return
        t0 = time.perf_counter()
        self._step(context, discrete_state, t0)
        self.wall_s += time.perf_counter() - t0

    def _command(self, t_s: float, q: np.ndarray) -> np.ndarray:
        """The source's command (4,) [v_W (3,) mm/s, roll rad/s] at t_s for the joint angles
        q (6,) rad (non-finite q gives a NaN tip, and the filter refuses the step)."""
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
        sensor_t = snap.healthy_t_s  # the newest healthy sensor sample, relayed by the model system
        rec = self.record
        pending = self.pending(context)
        out, P, ranges, J_tip, rcm_error = self.filter_step(t, q, command, snap, sensor_t, pending)
        if snap.stream and not out.ok and out.reason.startswith("stale sensor"):  # say what the stream sent
            out = out._replace(reason=out.reason.replace("stale sensor", f"stale sensor ({snap.stream})", 1))
        discrete_state.set_value(out.qdot)
        step_us = 1e6 * (time.perf_counter() - t0)
        if self.config.drake_diffik_every and len(rec.steps) % self.config.drake_diffik_every == 0 and out.ok:
            # Drake and the filter are timed on these after the run (ClosedLoop.run: time_references)
            rec.diffik_states.append((q, command[:3]))
            rec.keep_filter_state((q, command, self._times.copy(), self._fields, pending.copy(), self.p_WC))
        k = ranges[1, 1]  # the bounds on the points' true clearance; +inf after a fault (no barrier ran)
        bounds = np.full(k, np.inf) if not out.ok and out.min_clearance_mm != out.min_clearance_mm else \
            self.stack.point_bound[:k].copy()
        rec.steps.append(Step(t, q, out.qdot, command[:3], J_tip, out.ok, out.reason, out.intervened, out.solve_us,
                              step_us, out.min_clearance_mm, snap.kind, float(rcm_error), P[:ranges[1, 1]],
                              P[ranges[2, 0]:ranges[2, 1]], bounds))
        if self.logger is not None:
            meas = self._meas.Eval(context)
            self._log(t, q, command, snap, sensor_t, out, float(meas[0]) if meas[1] > 0 else float("nan"),
                      None if self._actuator is None else pending)

    def time_references(self) -> None:
        """Time Drake's DoDifferentialInverseKinematics on the states recorded during the
        run (every drake_diffik_every-th step the filter solved), into the record: the
        same plant and states as the filter, outside the run's wall time, one after the
        other. The filter's compiled step is timed the same way on a subsample of the same
        states (StepRecord.keep_filter_state; those of the run's last trocar: the stack holds
        its RCM), `filter_replay_us`: the two costs under the same conditions, where the
        run's own `solve_us` is the filter's in the loop, between the simulator's and the
        model's work."""
        rec = self.record
        for q, command, times, fields, pending, p_WC in rec.filter_states:
            if p_WC is self.p_WC:
                out = self.stack.solve_at(q, command, times, self._kp, fields, pending)[0]
                rec.filter_replay_us.append(out.solve_us)
        self.stack.reset()  # the replay's active set is no step's of the run
        for q, v_cmd in rec.diffik_states:
            t1 = time.perf_counter()
            self.drake_diffik(q, v_cmd)
            rec.drake_diffik_us.append(1e6 * (time.perf_counter() - t1))

    def _log(self, t: float, q, command, snap, sensor_t: float, out, distance_mm: float, pending) -> None:
        """Every step's compact record (eval.log.steps: what replay cannot recompute, with the
        actuator's `pending` displacements, None for an ideal one); joint
        states and clearances at 100 Hz; frames and the 3D scene (model, lens, trocar, the
        beam to the last measured distance) at 20 Hz."""
        log, k = self.logger, len(self.record.steps)
        P = self.record.steps[-1].points_W  # the compiled step's tip, port, shaft: instrument_points' kernel's
        prior = snap.shape is None or (self.local and snap.field is None)
        kind = None if prior else snap.kind
        model = self.prior if prior else snap.shape
        finite = bool(np.isfinite(q).all())
        if finite:  # non-finite joint angles: nothing the replay could re-run
            shape, kind, margin, trusted, misfit = self._step_model(snap, P)
            log.log_step(t, q, command, shape, kind, t if kind is None else snap.t_s, sensor_t, margin, trusted,
                         misfit, out, pending)
        if k % 10 == 1:
            log.log_joint_states(t, q, out.qdot, JOINT_NAMES)
            log.log_clearance(t, P[:2], model)
        self._log_events(t, kind, out)
        if k % 50 == 1 and finite:
            frames = self.robot_scene.link_poses(q)
            for name in ("F", "T", "S", "P"):
                R, p = self.robot.pose(name, q)
                X = np.eye(4)
                X[:3, :3], X[:3, 3] = R, p
                frames[name] = X
            log.log_frames(t, frames)
            o, u = self.robot.beam(q)
            beam = None if not np.isfinite(distance_mm) else (o, o + distance_mm * u)
            keep = self.config.filter.boundary_mm(0.0 if prior or self.local else float(snap.margin_mm(self.config.margins)))
            log.log_scene(t, eye=model, beam=beam, p_W_trocar=self.p_WC, lens=self.lens,
                          boundary=shrunk(model, keep), robot=self.robot_scene)

    def _log_events(self, t: float, kind: str | None, out) -> None:
        """/log: the filter stopping the robot (a fault: its reason) and resuming, the
        model the filter trusts changing kind."""
        log, last_ok, last_kind = self.logger, *self._logged_state
        if out.ok != last_ok:
            if out.ok:
                log.log_event(t, "filter resumed", "info")
            else:
                log.log_event(t, f"filter stop: {out.reason}", "warning")
        if kind != last_kind:
            log.log_event(t, f"model: {last_kind or 'prior'} -> {kind or 'prior'}", "info")
        self._logged_state = (out.ok, kind)
