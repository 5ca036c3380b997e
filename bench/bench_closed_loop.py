"""Closed-loop figures: realtime factor of adversarial scenarios on the emmetropic eye and
where a control step's time goes (monitored-point kinematics, filter, sensor packet,
model update), with Drake's DoDifferentialInverseKinematics on the same states."""
from __future__ import annotations

import time

import numpy as np

from bench.timing import summary_us, time_calls_us
from eval.experiments.boundary import build_model_by_spiral, run_campaign
from eval.closed_loop import ClosedLoop, ModelSnapshot
from safety import SafetyFilter
from planning import SurgeryScenario
from planning.instrument_points import instrument_points


def _empty_diagram_realtime_factor(duration_s: float = 2.0) -> float:
    """Realtime factor of the loop's diagram shape with empty callbacks (the filter at 1 kHz,
    a DiscreteTimeIntegrator, a 200 Hz abstract-state system feeding the filter; no sensor):
    what Drake's simulator costs before any of our per-step work."""
    from pydrake.common.value import AbstractValue
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder, LeafSystem
    from pydrake.systems.primitives import DiscreteTimeIntegrator

    def periodic(period_s: float, inputs: list, state: int | None):
        sys = LeafSystem()
        ports = [sys.DeclareAbstractInputPort(n, AbstractValue.Make(0)) if size is None else sys.DeclareVectorInputPort(n, size)
                 for n, size in inputs]
        def read_inputs(context, _state) -> None:  # the work every callback does at least
            for port in ports:
                port.Eval(context)

        if state is None:
            st = sys.DeclareAbstractState(AbstractValue.Make(0))
            sys.DeclarePeriodicUnrestrictedUpdateEvent(period_s, 0.0, read_inputs)
        else:
            st = sys.DeclareDiscreteState(state)
            sys.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, read_inputs)
        sys.DeclareStateOutputPort("out", st)
        return sys

    b = DiagramBuilder()
    filt = b.AddSystem(periodic(1e-3, [("q", 6), ("snap", None), ("measurement", 6)], 6))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 1e-3))
    model = b.AddSystem(periodic(5e-3, [("q", 6)], None))
    b.Connect(filt.get_output_port(), integ.get_input_port())
    for sink, port in ((filt, 0), (model, 0)):
        b.Connect(integ.get_output_port(), sink.get_input_port(port))
    b.Connect(model.get_output_port(), filt.get_input_port(1))
    b.Connect(integ.get_output_port(), filt.get_input_port(2))  # stands for the sensor's measurement
    sim = Simulator(b.Build())
    sim.Initialize()
    t0 = time.perf_counter()
    sim.AdvanceTo(duration_s)
    return duration_s / (time.perf_counter() - t0)


def _ms_per_s(runs, wall_field: str) -> float:
    """Wall time (ms) per simulated second of one system of the loop over runs (LoopRun or a list)."""
    runs = runs if isinstance(runs, list) else [runs]
    return 1e3 * sum(getattr(r, wall_field) for r in runs) / sum(r.duration_s for r in runs)


def _per_system(runs) -> str:
    """The command source's, the filter's and the model system's wall ms per simulated second over runs."""
    return ("  per simulated second: " + ", ".join(f"{name} {_ms_per_s(runs, f'{field}_wall_s'):.1f} ms" for name, field in
                                                  (("command source", "command"), ("filter", "filter"),
                                                   ("model system", "model")))
            + " (of the 100 ms that 10 x real time allows)")


def _sensor_ms_per_simulated_s(loop: ClosedLoop, q0: np.ndarray, duration_s: float = 1.0) -> float:
    """Wall ms per simulated second of the loop's sensor block (its rate and packets,
    distance mode, joint angles latched at the control rate as in the loop) on joint
    angles moving at every control step: a DiscreteTimeIntegrator feeding the block,
    minus the same integrator alone."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource, DiscreteTimeIntegrator

    from eval.systems.sensor import IioctSensorSystem
    from planning.iioct import IioctSensor

    def wall_s(with_sensor: bool) -> float:
        b = DiagramBuilder()
        src = b.AddSystem(ConstantVectorSource(np.array([0.02, 0.01, 0.0, 0.0, 0.0, 0.05])))  # rad/s
        integ = b.AddSystem(DiscreteTimeIntegrator(6, 1.0 / loop.config.control_rate_hz))
        b.Connect(src.get_output_port(), integ.get_input_port())
        if with_sensor:
            sensor = b.AddSystem(IioctSensorSystem(IioctSensor(loop.robot, mode="distance"), loop.config.sensor_rate_hz,
                                                   packet=loop.config.sensor_packet,
                                                   input_rate_hz=loop.config.control_rate_hz))
            b.Connect(integ.get_output_port(), sensor.GetInputPort("q"))
        sim = Simulator(b.Build())
        integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q0)
        sim.Initialize()
        t0 = time.perf_counter()
        sim.AdvanceTo(duration_s)
        return time.perf_counter() - t0

    return 1e3 * (np.median([wall_s(True) for _ in range(5)]) - min(wall_s(False) for _ in range(3))) / duration_s


def run() -> None:
    print(f"the loop's diagram with empty callbacks: realtime factor {_empty_diagram_realtime_factor():.0f} "
          "(Drake's own cost per step; the rest is ours)")
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario)
    build = build_model_by_spiral(loop, 17.0, pitch_mm=3.0, revolutions=3.0)
    print(f"spiral (3 turns, 17 mm/s): {build.run.duration_s:.2f} s simulated in {build.run.wall_s:.2f} s "
          f"(realtime factor {build.run.realtime_factor:.2f}); model {build.kind_final}, EF MAE {build.ef_mae_um:.1f} um")
    print(_per_system(build.run))
    c = run_campaign(loop, build.model, build.coverage, 10, seed=0, duration_s=0.5)
    s = c.summary()
    print(f"10 adversarial scenarios x 0.5 s: realtime factor {s['realtime_factor']:.2f}, "
          f"filter solve median {s['solve_us']['median']:.0f} us p99 {s['solve_us']['p99']:.0f} us, "
          f"Drake DoDifferentialInverseKinematics median {s['drake_diffik_us']['median']:.0f} us "
          f"p99 {s['drake_diffik_us']['p99']:.0f} us; the filter's step timed as Drake's, after the runs on the "
          f"same states: median {s['filter_replay_us']['median']:.0f} us p99 {s['filter_replay_us']['p99']:.0f} us")
    print(_per_system(c.runs))
    # the machine's speed drifts between runs (up to ~2x here): the same campaign again
    repeats = [run_campaign(loop, build.model, build.coverage, 10, seed=0, duration_s=0.5).summary()["realtime_factor"]
               for _ in range(4)]
    print(f"the same 10 scenarios 4 times more: realtime factor {', '.join(f'{x:.2f}' for x in repeats)} "
          f"(median of all 5: {np.median(repeats + [s['realtime_factor']]):.2f})")
    steps = np.concatenate([r.step_us for r in c.runs])
    print(f"filter step in the loop (compiled step, ports, record): {summary_us(steps)}")
    qs = np.concatenate([r.q for r in c.runs])[:2000]
    print(f"reference path: instrument_points:       {summary_us(time_calls_us(lambda i: instrument_points(loop.robot, qs[i], scenario.p_WC), len(qs)))}")
    f = loop.filter
    snap = ModelSnapshot(build.model.kind, build.model.shape, 0.0, 0.01, build.model.n_points, build.coverage.view(build.model.shape))
    cmd = np.array([5.0, 0.0, -3.0, 0.0])
    print(f"reference path: FilterSystem.inputs:     {summary_us(time_calls_us(lambda i: f.inputs(0.0, qs[i], cmd, snap, 0.0), len(qs)))}")
    xs = [f.inputs(0.0, q, cmd, snap, 0.0)[0] for q in qs[:500]]
    reference = SafetyFilter(loop.config.filter)
    print(f"reference path: SafetyFilter call:       {summary_us(time_calls_us(lambda i: reference(xs[i]), len(xs)))}")
    P = loop.config.sensor_packet
    packets = [qs[i:i + P] for i in range(0, len(qs) - P, P)]  # joint angles along the runs
    T = np.arange(P) / loop.config.sensor_rate_hz
    packet_us = time_calls_us(lambda i: loop.sensor.packet(packets[i], packets[i], T), len(packets))
    print(f"sensor packet of {P} (distance mode):     {summary_us(packet_us)}")
    ms = _sensor_ms_per_simulated_s(loop, qs[0])
    rate, per_packet = loop.config.sensor_rate_hz, loop.config.sensor_packet
    sample_us = 1e3 * (ms - 1e-3 * np.median(packet_us) * rate / per_packet) / rate
    print(f"sensor block in a diagram, 1 s at {rate:.0f} Hz: {ms:.1f} ms per simulated s (target <= 15); "
          f"per sample (the C++ latches' steps and the packet events' dispatch, the packets' median "
          f"taken off) {sample_us:.1f} us")
    upd = np.concatenate([r.model_update_us for r in c.runs])
    print(f"model update per A-scan (packets of {P}): {summary_us(upd)}")
