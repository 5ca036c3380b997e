"""Compact filter-step records: a few hundred bytes per step, decodable with the schema
the log carries, and replay rebuilds the filter's inputs from them (kinematics on the
logged scenario's robot) and catches a changed output."""
from __future__ import annotations

import gc
import weakref
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from eval.log.replay import replay
from eval.log.steps import STEP_TOPIC, STEP_TYPE, decode_step, setup_from_json, setup_to_json, values_of
from eval.log.writer import RunLogger, read_log
from eval.systems.inputs import StepInputs
from models import Sphere
from models.local.field import FieldValues
from planning import SurgeryScenario, start_posture
from planning.instrument_points import MonitoredPointsConfig
from planning.robot import Robot
from safety import FilterConfig, SafetyFilter

MAX_STEP_BYTES = 400  # 6 joint angles, 3 + 1 command, 6 rates: ~20 doubles, the flags and the reason


@pytest.fixture(scope="module")
def setup():
    scenario = SurgeryScenario(eye_name="myopic")
    robot = Robot(scenario)
    return scenario, robot, StepInputs(robot, MonitoredPointsConfig(), FilterConfig())


def _write(path, setup, tamper: int | None = None, steps: int = 30, models: list | None = None, while_open=None,
           values: bool = False):
    """A compact log of `steps` steps against a sphere model, outputs from SafetyFilter;
    step `tamper` logged with its rates changed by 1e-3 rad/s. With a list `models`: a new
    sphere (the same one, another object) every step, and a weak reference to each appended
    to it; `while_open` called after the last step, the log still open. With `values`: the
    sphere's answers at each step's boundary points as FieldValues, as the local boundary
    logs its field."""
    scenario, robot, build = setup
    filt = SafetyFilter(FilterConfig())
    model = Sphere(scenario.eye_pose.p_WE, 11.0)
    q = start_posture(robot, scenario.eye_pose.to_W(np.array([[0.5, 1.0, -4.0]]))[0], robot.p_WC)
    with RunLogger(path, FilterConfig()) as log:
        log.log_setup(setup_to_json(scenario, build.points, 10.0, 10.0))
        for k in range(steps):
            if models is not None:
                model = Sphere(scenario.eye_pose.p_WE, 11.0)
                models.append(weakref.ref(model))
            t = 0.011 + 1e-3 * k
            command = np.array([5.0, -2.0, -8.0, 0.0])
            ip = build.points_at(q)
            n = StepInputs.boundary_count("sphere", len(ip.names))
            trusted, misfit = np.ones(n, dtype=bool), np.full(n, 0.01)
            if values:
                P = ip.P_W[:n]
                model = FieldValues(P, *Sphere(scenario.eye_pose.p_WE, 11.0).signed_distance_and_gradient(P))
            out = filt(build(t, q, command, model, "sphere", t - 0.004, t - 0.001, 0.5, trusted, misfit, ip))
            logged = out._replace(qdot=out.qdot + 1e-3) if k == tamper else out
            log.log_step(t, q, command, model, "sphere", t - 0.004, t - 0.001, 0.5, trusted, misfit, logged)
            q = q + 1e-3 * out.qdot
        if while_open is not None:
            del model
            while_open()


def test_a_compact_log_replays_exactly_and_holds_few_bytes_per_step(setup, tmp_path):
    _write(tmp_path / "c.mcap", setup)
    result = replay(tmp_path / "c.mcap")
    assert result.ok and result.steps == 30 and result.max_abs_diff == 0.0
    sizes = [len(data) for _, data in read_log(tmp_path / "c.mcap").messages[STEP_TOPIC]]
    assert max(sizes) <= MAX_STEP_BYTES
    assert read_log(tmp_path / "c.mcap").count("/filter/models") == 1  # one model: logged once


def test_a_model_per_step_is_logged_per_step_and_not_held(setup, tmp_path):
    """The local boundary logs its field's values at the points every step (a new model
    object each time): each goes to /filter/models, the log replays, and the writer keeps
    none but the last (a long logged run would otherwise hold every step's)."""
    models, held = [], []

    def alive():
        gc.collect()
        held.extend(ref() is not None for ref in models)

    _write(tmp_path / "m.mcap", setup, steps=12, models=models, while_open=alive)
    assert held == [False] * 11 + [True]  # while the writer is open, only the last model is alive
    assert read_log(tmp_path / "m.mcap").count("/filter/models") == 12
    result = replay(tmp_path / "m.mcap")
    assert result.ok and result.steps == 12 and result.max_abs_diff == 0.0


def test_the_local_field_s_values_ride_in_the_step_records(setup, tmp_path):
    """The local boundary's per-step field values go into each step record (field_h,
    field_g), its model onto /filter/models once; the log replays bit for bit, and a
    record whose values do not match its boundary points is refused with the step named."""
    _write(tmp_path / "v.mcap", setup, steps=12, values=True)
    log = read_log(tmp_path / "v.mcap")
    assert log.count("/filter/models") == 1 and log.messages["/filter/models"][0][1]["shape"] == {"kind": "step_values"}
    records = [decode_step(data) for _, data in log.messages[STEP_TOPIC]]
    assert all(len(m.field_h) == len(m.misfit_mm) and len(m.field_g) == 3 * len(m.field_h) for m in records)
    assert all(-1.0 < min(m.field_h) and max(m.field_h) < 11.0 for m in records)  # mm inside an 11 mm sphere
    k = len(records[0].field_h)  # 4 doubles a point, two packed fields (a tag and a length each)
    assert max(len(data) for _, data in log.messages[STEP_TOPIC]) <= MAX_STEP_BYTES + 4 * 8 * k + 2 * 3
    result = replay(tmp_path / "v.mcap")
    assert result.ok and result.steps == 12 and result.max_abs_diff == 0.0
    with pytest.raises(ValueError, match="3 boundary points, but field_h holds 6 distances"):
        values_of(decode_step(log.messages[STEP_TOPIC][0][1]), np.zeros((3, 3)))


def test_a_changed_step_is_detected(setup, tmp_path):
    _write(tmp_path / "t.mcap", setup, tamper=7)
    result = replay(tmp_path / "t.mcap")
    assert result.mismatches == 1 and result.examples[0]["step"] == 7
    assert result.max_abs_diff == pytest.approx(1e-3, rel=1e-9)


def test_the_step_records_decode_with_the_schema_in_the_file(setup, tmp_path):
    """A reader with only the file (Foxglove) decodes the records: the schema is a
    protobuf FileDescriptorSet of vitreoguard.FilterStep."""
    _write(tmp_path / "s.mcap", setup, steps=3)
    with open(tmp_path / "s.mcap", "rb") as f:
        found = [(schema, message) for schema, channel, message in make_reader(f).iter_messages() if channel.topic == STEP_TOPIC]
    schema, message = found[0]
    assert schema.name == STEP_TYPE and schema.encoding == "protobuf"
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(fd)
    m = message_factory.GetMessageClass(pool.FindMessageTypeByName(STEP_TYPE)).FromString(message.data)
    assert m.step == 0 and len(m.q) == 6 and m.t == pytest.approx(0.011) and m.ok
    assert decode_step(message.data).SerializeToString() == m.SerializeToString()


def test_the_setup_rebuilds_the_scenario(setup):
    scenario, _, _ = setup
    back, points = setup_from_json(setup_to_json(scenario, MonitoredPointsConfig(), 10.0, 10.0))
    assert back.eye_name == "myopic" and points == MonitoredPointsConfig()
    np.testing.assert_array_equal(back.p_WC, scenario.p_WC)


def test_a_step_record_without_its_setup_is_refused(tmp_path):
    with RunLogger(tmp_path / "x.mcap", FilterConfig()) as log, pytest.raises(ValueError, match="log_setup"):
        log.log_step(0.0, np.zeros(6), np.zeros(4), None, None, 0.0, 0.0, 0.0, [True, True], [0.0, 0.0], None)


def test_a_log_with_the_field_values_as_json_model_records_replays():
    """Replay reads both forms of the local field's values at the boundary points: in the
    step records (RunLogger's) and as JSON records on /filter/models, one per step (points,
    distances, gradients; tests/data: a golden boundary case's first scenario in that form)."""
    path = Path(__file__).resolve().parents[1] / "data" / "boundary_local_values_json.mcap"
    log = read_log(path)
    assert log.messages["/filter/models"][-1][1]["shape"]["kind"] == "values"
    result = replay(path)
    assert result.ok and result.steps == log.count(STEP_TOPIC) > 100 and result.mismatches == 0
