"""The iiOCT sensor's Drake system: packets at 2 kHz against a brute-force recorder, the
time offset, runs started late, joint angles latched at 1 kHz, the register's reads."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, DiscreteTimeIntegrator

from eval.systems.sensor import IioctSensorSystem, SensorPacketProcessor
from planning import Robot, SurgeryScenario, start_posture
from planning.iioct import IioctSensor, SensorPacket


@pytest.fixture(scope="module")
def setup():
    """(scenario, robot, q): an RCM posture with the tip at (1, 2, -3) mm in the eye frame."""
    scenario = SurgeryScenario()
    robot = Robot(scenario)
    return scenario, robot, start_posture(robot, scenario.eye_pose.to_W(np.array([[1.0, 2.0, -3.0]]))[0], scenario.p_WC)


def _moving_diagram(robot, q0, qdot, offset_s, input_rate_hz=None):
    """q(t) = q0 + t qdot, integrated at 2 kHz (or at input_rate_hz, which the block is
    told), into the sensor block; returns (simulator, sensor system)."""
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(qdot))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 1.0 / (input_rate_hz or 2000.0)))
    sensor = b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet=10,
                                           input_rate_hz=input_rate_hz))
    b.Connect(src.get_output_port(), integ.get_input_port())
    b.Connect(integ.get_output_port(), sensor.GetInputPort("q"))
    d = b.Build()
    sim = Simulator(d)
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q0)
    return sim, sensor


def test_the_block_samples_at_2_khz_in_packets_and_the_time_offset_moves_the_points(setup):
    scenario, robot, q = setup
    qdot = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])  # rad/s
    out = {}
    for offset in (0.0, 0.002):
        sim, sensor = _moving_diagram(robot, q, qdot, offset)
        sim.AdvanceTo(0.0101)
        ctx = sensor.GetMyContextFromRoot(sim.get_context())
        packet = sensor.GetOutputPort("packet").Eval(ctx)
        m = sensor.GetOutputPort("measurement").Eval(ctx)
        assert packet.n_samples == 10 and np.allclose(np.diff(packet.t_s), 5e-4)
        assert m[3] == packet.t_s[-1] and m[1] == 1.0
        out[offset] = packet.sample(-1)
    # with the offset the beam is taken 2 ms earlier: the origin lags by |v_origin| x 2 ms
    o_then, _ = robot.beam(q + (out[0.0].t_s - 0.002) * qdot)
    np.testing.assert_allclose(out[0.002].beam_origin_W, o_then, atol=1e-9)
    lag = np.linalg.norm(out[0.002].beam_origin_W - out[0.0].beam_origin_W)
    v = np.linalg.norm(robot.jacobian("S", np.zeros(3), q) @ qdot)
    assert abs(lag - v * 0.002) < 0.05 * v * 0.002


class _Recorder(LeafSystem):
    """Brute-force reference: records (t, q) at every sample time with a discrete update
    at 2 kHz (the phase in which the sensor's q is read) into a Python list."""

    def __init__(self, rate_hz: float):
        super().__init__()
        self.rows: list = []
        self._q = self.DeclareVectorInputPort("q", 6)
        self.DeclareDiscreteState(1)
        self.DeclarePeriodicDiscreteUpdateEvent(1.0 / rate_hz, 0.0, self._record)

    def _record(self, context, discrete_state) -> None:
        self.rows.append((context.get_time(), np.array(self._q.Eval(context))))


@pytest.mark.parametrize("offset_s", [0.0, 0.0013])
def test_the_block_delivers_exactly_the_brute_force_reference_samples(setup, offset_s):
    """q changing at every sample (a 2 kHz integrator): each packet appears once, 10
    samples with the reference's time stamps (bit for bit) and beams at the reference's
    joint angles; with the same seed the samples equal the sensor's on the reference
    packets, field by field. With a time offset (2.6 samples: the first packets' points
    from before the first sample, held at it) the reported angles are the reference's
    history interpolated at t - offset."""
    scenario, robot, q = setup
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(np.array([0.05, -0.03, 0.02, 0.0, 0.04, 0.1])))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 5e-4))
    sensor = b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet=10))
    rec = b.AddSystem(_Recorder(2000.0))
    b.Connect(src.get_output_port(), integ.get_input_port())
    for sink in (sensor.GetInputPort("q"), rec.get_input_port()):
        b.Connect(integ.get_output_port(), sink)
    sim = Simulator(b.Build())
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q)
    packets = []
    for n in range(12):  # read between each packet event (t_last + 0.125 ms) and the next sample
        sim.AdvanceTo(n * 5e-3 + 4.8e-3)
        packets.append(sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context())))
    assert len({p.t_s[0] for p in packets}) == 12
    reference = IioctSensor(robot, mode="distance", seed=0)
    for n, packet in enumerate(packets):
        T = np.array([t for t, _ in rec.rows[10 * n:10 * n + 10]])
        Q = np.array([qq for _, qq in rec.rows[10 * n:10 * n + 10]])
        assert packet.t_s.tolist() == T.tolist()
        assert len(set(map(tuple, Q))) == 10  # q really changes at every sample
        t_all, q_all = np.array([t for t, _ in rec.rows]), np.array([qq for _, qq in rec.rows])
        Q_reported = np.column_stack([np.interp(T - offset_s, t_all, q_all[:, i]) for i in range(6)])
        r = reference.packet(Q, Q_reported, T)
        for name in ("distance_mm", "valid", "reasons", "true_distance_mm", "beam_origin_W", "p_W"):
            np.testing.assert_equal(getattr(packet, name), getattr(r, name))  # NaN equal to NaN


def test_a_run_started_late_packs_only_the_samples_recorded_since_its_start(setup):
    """A simulation starting at 3.1 ms: its first packet (processed at 4.625 ms) holds the
    samples at 3.5, 4.0 and 4.5 ms only (k x 0.5 ms, Drake's sample times), none of the
    register's unrecorded rows; with a 1.3 ms offset their points come from the first
    sample's joint angles (the history starts there)."""
    scenario, robot, q = setup
    qdot = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])  # rad/s
    sim, sensor = _moving_diagram(robot, q, qdot, 0.0013)
    sim.get_mutable_context().SetTime(0.0031)
    sim.Initialize()
    sim.AdvanceTo(0.0049)
    packet = sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context()))
    assert packet.t_s.tolist() == (np.arange(7, 10) * 5e-4).tolist()
    first = IioctSensor(robot, mode="distance").reported_beams(np.array([q]))[0][0]  # q at 3.5 ms: the integral's start
    np.testing.assert_array_equal(packet.beam_origin_W, np.tile(first, (3, 1)))


def test_a_run_started_after_a_packets_last_sample_has_no_packet_until_the_next(setup):
    """Started at 4.6 ms, between the last sample of the first packet (4.5 ms) and its
    event (4.625 ms): no sample yet at 4.9 ms (measurement t_s = -inf, not valid); at
    9.9 ms the packet of 5.0-9.5 ms."""
    scenario, robot, q = setup
    sim, sensor = _moving_diagram(robot, q, np.zeros(6), 0.0)
    sim.get_mutable_context().SetTime(0.0046)
    sim.Initialize()
    sim.AdvanceTo(0.0049)
    ctx = sensor.GetMyContextFromRoot(sim.get_context())
    m = sensor.GetOutputPort("measurement").Eval(ctx)
    assert m[3] == -np.inf and m[1] == 0.0
    sim.AdvanceTo(0.0099)
    packet = sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context()))
    assert packet.t_s.tolist() == (np.arange(10, 20) * 5e-4).tolist()


@pytest.mark.parametrize("packet", [10, 20])
@pytest.mark.parametrize("offset_s", [0.0, 0.0013])
def test_a_block_latching_1_khz_joint_angles_delivers_the_2_khz_registers_packets(setup, offset_s, packet):
    """q from a 1 kHz integrator into a block told so (input_rate_hz=1000: latches at whole
    ms) and a block with the default 2 kHz register: the same packets, every field bit for
    bit (NaN equal to NaN), each once. The default block processes a packet a quarter
    sample after its last sample, the 1 kHz one after the latch at the next whole ms
    (1.25 samples after it); each block is read between its processing and the next."""
    scenario, robot, q = setup
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(np.array([0.05, -0.03, 0.02, 0.0, 0.04, 0.1])))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 1e-3))
    blocks = [b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet,
                                            input_rate_hz=rate)) for rate in (None, 1000.0)]
    b.Connect(src.get_output_port(), integ.get_input_port())
    for block in blocks:
        b.Connect(integ.get_output_port(), block.GetInputPort("q"))
    sim = Simulator(b.Build())
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q)
    assert [block.packet_offset_s for block in blocks] == [(packet - 0.75) * 5e-4, (packet + 0.25) * 5e-4]
    packets = ([], [])
    for n in range(8):
        for block, out in zip(blocks, packets):
            sim.AdvanceTo(n * packet * 5e-4 + block.packet_offset_s + 1e-4)
            out.append(block.GetOutputPort("packet").Eval(block.GetMyContextFromRoot(sim.get_context())))
    for default, latched in zip(*packets):
        for name in SensorPacket._fields:
            np.testing.assert_equal(getattr(latched, name), getattr(default, name))  # NaN equal to NaN
    assert [p.t_s.tolist() for p in packets[1]] == [(np.arange(n * packet, (n + 1) * packet) * 5e-4).tolist()
                                                    for n in range(8)]
    d = packets[1][1].true_distance_mm  # samples 2j - 1 and 2j alike (q changes after each whole ms), no more
    assert d[1::2].tolist() == d[2::2].tolist() + [d[-1]] and len(set(d.tolist())) == packet // 2 + 1


def test_an_input_rate_that_does_not_divide_the_sample_rate_is_refused(setup):
    """So is a packet that is no multiple of the samples per latch."""
    scenario, robot, q = setup
    for input_rate_hz in (3000.0, 0.0, np.nan, 1500.0):
        with pytest.raises(ValueError, match=r"input_rate_hz must be rate_hz / r .*2000, 1000, 666.667, \.\.\. Hz"):
            IioctSensorSystem(IioctSensor(robot), 2000.0, input_rate_hz=input_rate_hz)
    with pytest.raises(ValueError, match="packet must be a multiple of rate_hz / input_rate_hz = 2 samples"):
        IioctSensorSystem(IioctSensor(robot), 2000.0, packet=5, input_rate_hz=1000.0)


@pytest.mark.parametrize("start_s, first", [(0.0031, 7), (0.0036, 8), (0.0046, 10)])
def test_a_run_started_late_on_1_khz_joint_angles_packs_only_the_samples_since_its_start(setup, start_s, first):
    """q integrated and latched at 1 kHz, the packet of 0-4.5 ms processed at 5.125 ms. A
    run started mid-packet, at 3.1 or 3.6 ms, packs the samples from its start on (3.5 or
    4.0 ms to 4.5 ms: at 3.6 ms the 4 ms latch covers the 3.5 ms sample too, which is
    left out), with a 1.3 ms offset their points from the first sample's joint angles
    (the history starts there); a run started at 4.6 ms, after the packet's last sample
    (which the 5 ms latch covers), has no packet until the next, that of 5.0-9.5 ms."""
    scenario, robot, q = setup
    sim, sensor = _moving_diagram(robot, q, np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.0013, input_rate_hz=1000.0)
    sim.get_mutable_context().SetTime(start_s)
    sim.Initialize()
    sim.AdvanceTo(sensor.packet_offset_s + 2e-4)
    ctx = sensor.GetMyContextFromRoot(sim.get_context())
    packet, m = sensor.GetOutputPort("packet").Eval(ctx), sensor.GetOutputPort("measurement").Eval(ctx)
    if first < 10:
        assert packet.t_s.tolist() == (np.arange(first, 10) * 5e-4).tolist()
        beam_at_start = IioctSensor(robot, mode="distance").reported_beams(np.array([q]))[0][0]
        np.testing.assert_array_equal(packet.beam_origin_W, np.tile(beam_at_start, (10 - first, 1)))
    else:
        assert m[3] == -np.inf and m[1] == 0.0
    sim.AdvanceTo(sensor.packet_offset_s + 5.2e-3)
    packet = sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context()))
    assert packet.t_s.tolist() == (np.arange(10, 20) * 5e-4).tolist()


@settings(max_examples=20)
@given(start_s=st.floats(0.0, 0.012), input_rate_hz=st.sampled_from([None, 1000.0]),
       offset_s=st.sampled_from([0.0, 0.0013]))
def test_a_full_registers_fast_read_is_the_general_one(setup, start_s, input_rate_hz, offset_s):
    """A run started at a random time, q moving at every latch: at each of the first 6
    packet events after the start the processor's joint angles are, bit for bit, those of
    the general read (JointRegister.recorded_since, filtered by the run's start time);
    the fast read (recorded_full, without the start time) gives them from the third packet
    on, and not for the first (the sentinel not yet recorded)."""
    scenario, robot, q = setup
    sim, sensor = _moving_diagram(robot, q, np.array([0.05, -0.03, 0.02, 0.0, 0.04, 0.1]), offset_s, input_rate_hz)
    processor = next(s for s in sensor.GetSystems() if isinstance(s, SensorPacketProcessor))
    sim.get_mutable_context().SetTime(start_s)
    sim.Initialize()
    fast = []
    first = int(np.floor((start_s - sensor.packet_offset_s) / 5e-3)) + 1  # the first packet event after the start
    for t in sensor.packet_offset_s + 5e-3 * np.arange(max(first, 0), max(first, 0) + 6):
        sim.AdvanceTo(t)
        context = processor.GetMyContextFromRoot(sim.get_context())
        register, t_s = processor.GetInputPort("register").Eval(context), context.get_time()
        T_ref, Q_ref = processor.register.recorded_since(register, t_s, processor.start_time_s(context))
        full = processor.register.recorded_full(register, t_s)
        fast.append(full is not None)
        for T, Q in [processor.recorded(context)] + ([] if full is None else [full]):
            assert T.tobytes() == T_ref.tobytes() and Q.tobytes() == Q_ref.tobytes()
            assert Q.shape == (len(T), 6) and Q.flags.c_contiguous
    assert not fast[0] and all(fast[2:])
