"""The iiOCT sensor as a Drake system: joint angles in, packets of samples out.

A diagram of Drake's C++ primitives and one Python system: a shift register of the
latched joint angles (a ZeroOrderHold fed by a Selector from its own value, a constant 1
and "q"; planning.iioct.JointRegister describes its rows) and `SensorPacketProcessor`,
which reads the whole register at the packet rate and asks the sensor model
(planning.iioct.IioctSensor) for the packet.

Units: s, Hz, rad; mm and frame W in the outputs.
"""
from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, Selector, SelectorParams, ZeroOrderHold

from planning.iioct import NO_SAMPLE_YET, IioctSensor, JointRegister, SensorPacket, rate_ratio
from planning.iioct.latches import REGISTER_ROW, delayed_angles
from planning.iioct.stream import StreamFault


def _shift_selector(rows: int) -> Selector:
    """A Selector giving the shift register's next value from its inputs "register"
    (`rows` rows of [recorded flag, q (6) rad], oldest first, flattened), "one" (1,) and
    "q" (6,) rad: the register without its oldest row, then [1, q]."""
    S = SelectorParams
    kept = [S.OutputSelection(input_port_index=0, input_offset=i) for i in range(REGISTER_ROW, REGISTER_ROW * rows)]
    new = [S.OutputSelection(input_port_index=1, input_offset=0)]
    new += [S.OutputSelection(input_port_index=2, input_offset=i) for i in range(6)]
    return Selector(S(inputs=[S.InputPortParams(name="register", size=REGISTER_ROW * rows),
                              S.InputPortParams(name="one", size=1), S.InputPortParams(name="q", size=6)],
                      outputs=[S.OutputPortParams(name="shifted", selections=kept + new)]))


class SensorPacketProcessor(LeafSystem):
    """Turns the register's latched joint angles into the packet of the newest `packet`
    samples, in one unrestricted update at the packet rate (IioctSensorSystem), at the
    times of `register` (a planning.iioct.JointRegister: the first at its offset_s, then
    every packet sample periods). Input "register" (7 register.slots,): its rows,
    oldest first, flattened; outputs as IioctSensorSystem's. The joint angles of the
    samples are read without the run's start time once the register's sentinel is
    recorded (every packet of a run but the first one or two), else filtered by the
    start time an initialisation event notes."""

    def __init__(self, sensor: IioctSensor, register: JointRegister, time_offset_s: float,
                 stream_fault: StreamFault = StreamFault()):
        super().__init__()
        self.sensor, self.register, self.time_offset_s = sensor, register, time_offset_s
        self.stream_fault = stream_fault
        self._register = self.DeclareVectorInputPort("register", REGISTER_ROW * register.slots)
        self._packet = self.DeclareAbstractState(AbstractValue.Make(NO_SAMPLE_YET))
        self._packet_at = int(self._packet)  # the same index as an int, which pybind takes faster per packet
        self._start = self.DeclareDiscreteState(1)  # the run's start time, s
        self.DeclareInitializationDiscreteUpdateEvent(self._set_start)
        self.DeclarePeriodicUnrestrictedUpdateEvent(register.packet * register.period_s, register.offset_s,
                                                    self._process)
        packet_changed = {self.abstract_state_ticket(self._packet)}
        self.DeclareStateOutputPort("packet", self._packet)
        self.DeclareAbstractOutputPort("sample", lambda: AbstractValue.Make(NO_SAMPLE_YET.sample(0)),
                                       self._calc_sample, prerequisites_of_calc=packet_changed)
        self.DeclareVectorOutputPort("p_W", 3, self._calc_p, prerequisites_of_calc=packet_changed)
        self.DeclareVectorOutputPort("measurement", 4, self._calc_measurement, prerequisites_of_calc=packet_changed)

    def _set_start(self, context, discrete_state) -> None:
        discrete_state.set_value([context.get_time()])

    def start_time_s(self, context) -> float:
        """The run's start time (s), noted by the initialisation event."""
        return context.get_discrete_state(self._start).GetAtIndex(0)

    def recorded(self, context) -> tuple[np.ndarray, np.ndarray]:
        """((K,) time stamps s, (K, 6) joint angles rad) of the samples the register's
        recorded latches cover at the context's time, from the run's start to the packet's
        last sample, oldest first (JointRegister.recorded_full, else recorded_since)."""
        register, t = self._register.Eval(context), context.get_time()
        full = self.register.recorded_full(register, t)
        return self.register.recorded_since(register, t, self.start_time_s(context)) if full is None else full

    def _process(self, context, state) -> None:
        T_all, Q_all = self.recorded(context)
        if not len(T_all):  # a run started after this packet's last sample: keep the previous packet
            return
        T, Q = T_all[-self.register.packet:], Q_all[-self.register.packet:]
        packet = self.sensor.packet_of_arrays(T, Q, delayed_angles(T, T_all, Q_all, self.time_offset_s))
        if self.stream_fault.kind != "none":
            previous = self._latest(context)
            packet = self.stream_fault.apply(packet, None if previous is NO_SAMPLE_YET else previous)
            if packet is None:  # no new packet
                return
        state.get_mutable_abstract_state(self._packet_at).set_value(packet)

    def _latest(self, context) -> SensorPacket:
        return context.get_abstract_state(self._packet_at).get_value()

    def _calc_sample(self, context, value) -> None:
        value.set_value(self._latest(context).sample(-1))

    def _calc_p(self, context, output) -> None:
        output.SetFromVector(self._latest(context).p_W[-1])

    def _calc_measurement(self, context, output) -> None:
        p = self._latest(context)
        output.SetFromVector([p.distance_mm[-1], float(p.valid[-1]), p.confidence[-1], p.t_s[-1]])


class IioctSensorSystem(Diagram):
    """The sensor as a Drake block, sampling at `rate_hz` (default 2 kHz).

    Input "q" (6,) rad: the robot's joint angles. The OCT engine streams its A-scans in
    packets of `packet` samples (default 10, i.e. 5 ms at 2 kHz): each sample gets the
    joint angles held at its time, and the packet is processed once its last sample's
    angles are recorded (vectorised geometry). Outputs: "packet" (the latest packet, a
    SensorPacket; NO_SAMPLE_YET before the first), "sample" (its last sample, a
    SensorSample), "p_W" (3,) mm of that sample (NaN when invalid), "measurement" (4,)
    [distance_mm, valid 0/1, confidence, t_s] (t_s = -inf before the first packet).
    With `time_offset_s` (s) > 0 the points are reconstructed from the joint angles of
    `time_offset_s` earlier (the paper's OCT-robot synchronisation error, up to 2.6 ms),
    interpolated linearly in the recorded history.

    `stream_fault` (planning.iioct.stream.StreamFault): a degenerate stream injected from
    its onset on (default none).

    `input_rate_hz` (Hz; None: rate_hz) is the modelling assumption on q: a zero-order
    hold that changes only at whole multiples of 1 / input_rate_hz s (like the closed
    loop's DiscreteTimeIntegrator), an event at one of those times seeing the value
    before its change. rate_hz / input_rate_hz must be an integer r >= 1 (within a
    relative 1e-9) and `packet` a multiple of r. The joint angles are latched only at
    those times (planning.iioct.JointRegister). The packets are those of r = 1, bit for
    bit, for one Drake step per latch rather than one per sample (half the steps for a
    2 kHz sensor on 1 kHz joint angles); a q that changes between latches breaks the
    assumption: wrong angles, no warning.

    The register is a ZeroOrderHold with period 1 / input_rate_hz and offset 0 (Drake's
    discrete update at every latch time, its times computed like those of a
    DiscreteTimeIntegrator of that period). The packet is read a quarter of a sample
    period after the latch covering its last sample (`packet_offset_s`, s, for the first
    packet, then every packet / rate_hz s: a quarter sample after the last sample for
    r = 1, 1.25 samples after it for r > 1), and sample k is stamped k / rate_hz as Drake
    computes it (k x period), a register update's time at every sample, bit for bit. A
    run started mid-packet packs only the samples at or after its start time. Not at the
    latch's own time: there the register would not hold that latch yet (events at one
    time see the state before them), and Drake computes each periodic series' times on
    its own (offset + k period), so coinciding times can differ by rounding and a packet
    event a few ulps after a register step be skipped. A reader at the same time as the
    packet event sees the previous packet; the closed loop's model reads a quarter sample
    period after the packet event, the filter at whole control periods.
    """

    def __init__(self, sensor: IioctSensor, rate_hz: float = 2000.0, time_offset_s: float = 0.0, packet: int = 10,
                 input_rate_hz: float | None = None, stream_fault: StreamFault = StreamFault()):
        super().__init__()
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be > 0 Hz, got {rate_hz}")
        if not (np.isfinite(time_offset_s) and 0 <= time_offset_s <= 0.1):
            raise ValueError(f"time_offset_s must be in [0, 0.1] s, got {time_offset_s}")
        if not (isinstance(packet, int) and 1 <= packet <= 1000):
            raise ValueError(f"packet must be an int in [1, 1000] samples, got {packet}")
        self.sensor, self.rate_hz, self.time_offset_s, self.packet = sensor, float(rate_hz), float(time_offset_s), packet
        if input_rate_hz is None:
            input_rate_hz = self.rate_hz
        ratio = rate_ratio(self.rate_hz, input_rate_hz)
        if ratio is None:
            raise ValueError(f"input_rate_hz must be rate_hz / r for an integer r >= 1 ({self.rate_hz:g}, "
                             f"{self.rate_hz / 2:g}, {self.rate_hz / 3:g}, ... Hz), got {input_rate_hz}")
        if packet % ratio:
            raise ValueError(f"packet must be a multiple of rate_hz / input_rate_hz = {ratio} samples, got {packet}")
        self.input_rate_hz = float(input_rate_hz)
        # samples recorded before the packet's, kept for the offset's interpolation
        history = int(np.ceil(time_offset_s * rate_hz)) + 1 if time_offset_s > 0 else 0
        latches = JointRegister(self.rate_hz, ratio, packet, history)
        self.packet_offset_s = latches.offset_s  # s: the first packet's processing time (then every packet / rate_hz s)
        b = DiagramBuilder()
        processor = b.AddSystem(SensorPacketProcessor(sensor, latches, self.time_offset_s, stream_fault))
        register = b.AddSystem(ZeroOrderHold(1.0 / self.input_rate_hz, REGISTER_ROW * latches.slots))
        shift = b.AddSystem(_shift_selector(latches.slots))
        one = b.AddSystem(ConstantVectorSource([1.0]))
        b.Connect(register.get_output_port(), shift.get_input_port(0))
        b.Connect(one.get_output_port(), shift.get_input_port(1))
        b.Connect(shift.get_output_port(0), register.get_input_port())
        b.Connect(register.get_output_port(), processor.GetInputPort("register"))
        b.ExportInput(shift.get_input_port(2), "q")
        for name in ("packet", "sample", "p_W", "measurement"):
            b.ExportOutput(processor.GetOutputPort(name), name)
        b.BuildInto(self)
