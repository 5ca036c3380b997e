"""The MCAP run log: channels and schemas, exact encoding, Foxglove geometry, and a killed
writer's log. The synthetic run: the Cartesian toy robot of tests/safety/test_filter.py
(joints = tip coordinates, J = I, mm/rad) in a spherical retina of radius 12 mm."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from foxglove.messages import LogLevel
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from eval.log import codec
from eval.log import writer as writer_module
from eval.log.writer import M_PER_MM, RunLogger, quaternion_xyzw, read_log
from eval.log.scene import MESSAGES as FOXGLOVE_MESSAGES
from models import AdaptiveEyeModel, Ellipsoid, Sphere
from safety import FilterConfig, FilterInputs, PointKinematics, SafetyFilter

EYE = Sphere(np.zeros(3), 12.0)
DT = 1e-3
PORT_OFFSET = np.array([0.3, 0.0, 0.0])  # the cutter port, rigidly beside the tip (mm)
TOPICS = {"/filter/config", "/robot/joint_states", "/oct/ascan", "/oct/distance", "/model", "/filter/inputs",
          "/filter/outputs", "/filter/status", "/clearance", "/tf", "/scene"}


def toy_inputs(p, v_cmd, t, model=EYE, **kw) -> FilterInputs:
    p = np.asarray(p, float)
    points = [PointKinematics("tip", p, np.eye(3)), PointKinematics("port", p + PORT_OFFSET, np.eye(3))]
    return FilterInputs(t_s=t, q=p, q_min=np.full(3, -50.0), q_max=np.full(3, 50.0), qdot_max=np.full(3, 100.0),
                        v_cmd_W=np.asarray(v_cmd, float), J_tip=np.eye(3), boundary_points=points, model=model,
                        model_time_s=t, sensor_time_s=t, **kw)


def toy_step(log: RunLogger, filt: SafetyFilter, k: int, p: np.ndarray) -> np.ndarray:
    """Log step k of a circling push into the retina (the filter intervenes near the
    margin) with every channel; return the next tip position."""
    t = k * DT
    v_cmd = [5.0 * math.cos(3.0 * t), 5.0 * math.sin(3.0 * t), -8.0]
    x = toy_inputs(p, v_cmd, t)
    out = filt(x)
    log.log_filter_step(x, out, true_eye=EYE)
    log.log_joint_states(t, p, out.qdot, ["x", "y", "z"])
    log.log_distance(t, float(EYE.signed_distance(p)[0]), True, 0.9)
    if k % 10 == 0:
        log.log_ascan(t, np.exp(-0.5 * (np.arange(256) - 100.0) ** 2), True)
        log.log_model(t, "sphere", sphere=EYE, n_points=k, criteria={"scan_range": (0.1 * k, False)})
        log.log_frames(t, {"T": np.block([[np.eye(3), p[:, None]], [np.zeros((1, 3)), 1.0]])})
        log.log_scene(t, eye=EYE, beam=(p, p + [0.0, 0.0, -3.0]), p_W_trocar=[0.0, 0.0, 8.0],
                      lens=Ellipsoid([0.0, 0.0, 7.8], [4.5, 4.5, 2.0]))
    return p + DT * out.qdot


def write_toy_run(path, steps: int, config: FilterConfig | None = None, flush_every_s: float = 1.0,
                  start_ns: int | None = None) -> Path:
    filt = SafetyFilter(config)
    p = np.array([0.0, 0.0, -10.0])
    with RunLogger(path, filt.config, flush_every_s=flush_every_s, start_ns=start_ns) as log:
        for k in range(steps):
            p = toy_step(log, filt, k, p)
    return Path(path)


@pytest.fixture(scope="module")
def toy_log(tmp_path_factory) -> Path:
    return write_toy_run(tmp_path_factory.mktemp("log") / "run.mcap", 300)


JSON_TOPICS = TOPICS - set(FOXGLOVE_MESSAGES)


def foxglove_class(schema_data: bytes, name: str):
    """The protobuf message class `name` (e.g. "foxglove.SceneUpdate") of a protobuf
    schema record's data (a FileDescriptorSet, as foxglove-sdk writes it)."""
    files = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for fd in files.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def decode_foxglove(topic: str, data: bytes):
    """A Foxglove message of `topic` decoded with the SDK's published schema."""
    schema = FOXGLOVE_MESSAGES[topic].get_schema()
    return foxglove_class(schema.data, schema.name).FromString(data)


def test_the_log_has_every_channel_with_its_schema(toy_log):
    with open(toy_log, "rb") as f:
        reader = make_reader(f)  # mcap's own reader, through the summary
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == TOPICS  # "/log" holds run events: none in a run that ends normally
        for topic, c in topics.items():
            schema = summary.schemas[c.schema_id]
            if topic in JSON_TOPICS:
                assert c.message_encoding == "json" and schema.encoding == "jsonschema"
                assert json.loads(schema.data)["type"] == "object"
            else:  # Foxglove's published schema, as foxglove-sdk defines it, and its name
                published = FOXGLOVE_MESSAGES[topic].get_schema()
                assert c.message_encoding == schema.encoding == published.encoding == "protobuf"
                assert (schema.name, schema.data) == (published.name, published.data)
        assert summary.schemas[topics["/tf"].schema_id].name == "foxglove.FrameTransforms"
        assert summary.schemas[topics["/scene"].schema_id].name == "foxglove.SceneUpdate"
        counts = {topics_id: n for topics_id, n in summary.statistics.channel_message_counts.items()}
        by_topic = {c.topic: counts.get(cid, 0) for cid, c in summary.channels.items()}
        assert by_topic["/filter/inputs"] == by_topic["/filter/outputs"] == by_topic["/filter/status"] == 300
        assert by_topic["/filter/config"] == 1 and by_topic["/scene"] == by_topic["/tf"] == 30


def test_log_times_are_the_runs_wall_clock_start_plus_the_simulation_time(tmp_path):
    """Foxglove shows the run at the date it ran (not in 1970); the simulation time stays
    in the messages (`t`, and the scene entities' 'sim_time_s')."""
    before = time.time_ns()
    path = write_toy_run(tmp_path / "clock.mcap", 100)
    after = time.time_ns()
    log = read_log(path)
    start = log.start_ns
    assert before <= start <= after
    assert log.metadata["time"]["start_time_ns"] == str(start)
    for topic in JSON_TOPICS - {"/filter/config"}:
        for log_time, m in log.messages[topic]:
            assert log_time == start + round(m["t"] * 1e9)
    assert log.messages["/filter/config"][0][0] == start
    with open(path, "rb") as f:
        assert all(m.publish_time == m.log_time for _, _, m in make_reader(f).iter_messages())
    for (log_time, data), (_, inputs) in zip(log.messages["/scene"], log.messages["/filter/inputs"][::10]):
        entities = decode_foxglove("/scene", data).entities
        assert {kv.key: kv.value for kv in entities[0].metadata} == {"sim_time_s": repr(inputs["t"])}
        assert all(e.timestamp.seconds * 10**9 + e.timestamp.nanos == log_time for e in entities)
    for log_time, data in log.messages["/tf"]:
        (transform,) = decode_foxglove("/tf", data).transforms
        assert transform.timestamp.seconds * 10**9 + transform.timestamp.nanos == log_time
    given = read_log(write_toy_run(tmp_path / "given.mcap", 5, start_ns=1_700_000_000_123_456_789))
    assert given.start_ns == 1_700_000_000_123_456_789
    assert given.messages["/filter/inputs"][3][0] == 1_700_000_000_123_456_789 + 3_000_000


def test_a_run_stopped_by_an_exception_says_so_in_its_closed_log(tmp_path):
    """Ctrl-C (KeyboardInterrupt) or an error inside `with RunLogger(...)`: the log is
    complete (summary written) and ends with a foxglove.Log event naming the cause."""
    filt, p = SafetyFilter(), np.array([0.0, 0.0, -10.0])
    with pytest.raises(KeyboardInterrupt):
        with RunLogger(tmp_path / "stopped.mcap", filt.config) as log:
            for k in range(50):
                p = toy_step(log, filt, k, p)
            raise KeyboardInterrupt
    assert log.closed
    stopped = read_log(tmp_path / "stopped.mcap")  # not truncated: it was closed
    (log_time, data), = stopped.messages["/log"]
    event = decode_foxglove("/log", data)
    assert event.message == "run ended early: KeyboardInterrupt" and event.level == LogLevel.Error.value
    assert log_time == stopped.messages["/filter/inputs"][-1][0]  # at the last step's time


_JSON_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None),
               "number": (int, float), "integer": int}


def schema_violations(value, schema, where="") -> list[str]:
    """What in `value` breaks the JSON `schema` (types, required and undeclared fields,
    recursively): the subset of JSON Schema our schemas use."""
    types = schema.get("type")
    if types is not None:
        types = [types] if isinstance(types, str) else types
        ok = any(isinstance(value, _JSON_TYPES[t]) and not (t in ("number", "integer") and isinstance(value, bool))
                 for t in types)
        if not ok:
            return [f"{where}: {type(value).__name__} is not {types}"]
    out = []
    if isinstance(value, dict) and "properties" in schema:
        out += [f"{where}.{k}: required" for k in schema.get("required", ()) if k not in value]
        out += [f"{where}.{k}: undeclared" for k in value if k not in schema["properties"]]
        for k, v in value.items():
            out += schema_violations(v, schema["properties"].get(k, {}), f"{where}.{k}")
    if isinstance(value, list) and "items" in schema:
        for i, v in enumerate(value):
            out += schema_violations(v, schema["items"], f"{where}[{i}]")
    return out


def test_every_message_matches_its_schema(toy_log):
    """Every field a JSON message carries is declared with its type in the channel's schema
    (what Foxglove's panels offer for plotting), and the required ones are present; every
    Foxglove message decodes with Foxglove's published schema (foxglove-sdk's), with no
    field that schema lacks."""
    with open(toy_log, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic in JSON_TOPICS:
                assert schema_violations(json.loads(message.data), json.loads(schema.data), channel.topic) == []
            else:
                m = decode_foxglove(channel.topic, message.data)
                assert m.SerializeToString() == message.data  # nothing unknown to the schema
                m.DiscardUnknownFields()
                assert m.SerializeToString() == message.data


def test_filter_messages_hold_the_step(toy_log):
    log = read_log(toy_log)
    (_, inputs), (_, out), (_, status), (_, clearance) = (log.messages[t][150] for t in
                                                         ("/filter/inputs", "/filter/outputs", "/filter/status", "/clearance"))
    assert inputs["step"] == out["step"] == status["step"] == 150
    x = codec.inputs_from_json(inputs)
    assert x.t_s == pytest.approx(0.150, abs=1e-15) and x.model.radius == 12.0
    # clearance: the sphere's exact distance, 12 - |p| for the tip, 12 - |p + port offset| for the port
    assert clearance["tip_mm"] == pytest.approx(12.0 - np.linalg.norm(x.q), abs=1e-12)
    assert clearance["port_mm"] == pytest.approx(12.0 - np.linalg.norm(x.q + PORT_OFFSET), abs=1e-12)
    assert clearance["tip_true_mm"] == clearance["tip_mm"]
    assert set(status) >= {"ok", "reason", "active", "min_clearance_mm", "cutter_allowed", "intervened", "solve_us"}
    assert len(out["qdot"]) == 3


def test_the_run_pushes_the_filter_to_its_boundary(toy_log):
    """The synthetic run is worth replaying: it starts free with the cutter allowed (port
    clearance 2.0 mm) and ends held at the margin (the port, nearest the retina, at d_safe
    plus the calibration margin)."""
    log = read_log(toy_log)
    status = [m for _, m in log.messages["/filter/status"]]
    assert all(s["ok"] for s in status)
    assert not status[0]["intervened"] and status[0]["cutter_allowed"]
    assert status[-1]["active"] == ["boundary:port"] and not status[-1]["cutter_allowed"]
    port = [m["port_mm"] for _, m in log.messages["/clearance"]]
    margin = 0.5 + FilterConfig().calibration_margin_mm  # d_safe and the declared calibration bound
    assert min(port) >= margin - 1e-6 and port[-1] < margin + 0.05  # held at the margin by the barrier


def test_foxglove_geometry_is_in_metres(toy_log):
    log = read_log(toy_log)
    (_, tf), (scene_time, scene) = log.messages["/tf"][5], log.messages["/scene"][5]
    tf, scene = decode_foxglove("/tf", tf), decode_foxglove("/scene", scene)
    x = codec.inputs_from_json(log.messages["/filter/inputs"][50][1])  # the same time: step 50
    (transform,) = tf.transforms
    assert (transform.parent_frame_id, transform.child_frame_id) == ("W", "T")
    np.testing.assert_allclose([getattr(transform.translation, a) for a in "xyz"], M_PER_MM * x.q, atol=1e-15)
    entities = {e.id: e for e in scene.entities}
    assert set(entities) == {"eye_model", "lens", "beam", "trocar"}
    eye_size = entities["eye_model"].spheres[0].size
    assert [getattr(eye_size, a) for a in "xyz"] == pytest.approx([0.024] * 3)  # 2 x 12 mm, in metres
    lens_size = entities["lens"].spheres[0].size
    assert [getattr(lens_size, a) for a in "xyz"] == pytest.approx([0.009, 0.009, 0.004])
    beam = entities["beam"].lines[0].points
    assert beam[1].z - beam[0].z == pytest.approx(-0.003)
    assert all(e.frame_id == "W" for e in entities.values())
    assert all(e.timestamp.seconds * 10**9 + e.timestamp.nanos == scene_time == log.start_ns + 50_000_000
               for e in entities.values())


def _matrix_of(q):
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@settings(max_examples=200)
@given(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_quaternion_gives_back_the_rotation(v):
    v = np.asarray(v) / np.linalg.norm(v)
    R = _matrix_of(v)
    q = quaternion_xyzw(R)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12) and q[3] >= 0.0
    np.testing.assert_allclose(_matrix_of(q), R, atol=1e-12)


def same_bits(a, b) -> bool:
    """Equal to the bit, signed zeros included; any NaN equals any NaN (payloads carry
    no meaning here and JSON has one NaN)."""
    a, b = (np.where(np.isnan(v), np.nan, v) for v in (np.asarray(a, float), np.asarray(b, float)))
    return a.shape == b.shape and a.tobytes() == b.tobytes()


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=100)
@given(st.lists(finite_or_not, min_size=3, max_size=3), st.lists(finite_or_not, min_size=9, max_size=9),
       finite_or_not, st.floats(-1e6, 1e6), st.booleans())
def test_inputs_round_trip_bit_for_bit(v, J, margin, roll, ellipsoid):
    """Every float comes back with the same bits, NaN and inf included (faults are logged too)."""
    R = _matrix_of(np.array([0.3, -0.2, 0.5, 0.8]) / np.linalg.norm([0.3, -0.2, 0.5, 0.8]))
    model = Ellipsoid([0.1, -0.2, 0.3], [11.0, 11.5, 10.0], R) if ellipsoid else EYE
    x = toy_inputs([0.0, 0.0, -10.0], v, 0.25, model=model, rcm_A=np.reshape(J, (3, 3))[:2], rcm_b=np.array([roll, 0.0]),
                   lens=Ellipsoid([0, 0, 7.8], [4.5, 4.5, 2.0]), lens_points=[PointKinematics("shaft", np.array(v), np.eye(3))],
                   margin_mm=margin, J_roll=np.reshape(J, (3, 3))[2], roll_rate_cmd=roll)
    y = codec.inputs_from_json(json.loads(json.dumps(codec.inputs_to_json(x), allow_nan=False)))
    for name in ("q", "v_cmd_W", "J_tip", "rcm_A", "rcm_b", "J_roll", "margin_mm", "roll_rate_cmd", "t_s"):
        assert same_bits(getattr(y, name), getattr(x, name)), name
    assert [p.name for p in y.boundary_points] == ["tip", "port"]
    assert same_bits(y.lens_points[0].p_W, v)
    for a, b in ((x.model, y.model), (x.lens, y.lens)):
        assert type(a) is type(b) and a.center.tobytes() == b.center.tobytes()
    if ellipsoid:
        assert y.model.rotation.tobytes() == R.tobytes() and y.model.radii.tobytes() == x.model.radii.tobytes()


def test_model_updates_and_run_metadata_are_logged(tmp_path):
    """An adaptive model's history entry (sphere phase, 200 points on the 12 mm retina)
    lands on /model with its fit and criteria; run metadata in the file's metadata."""
    model = AdaptiveEyeModel(gate=None)  # a grid of samples, not A-scans in order: no jump gate
    update = model.update(EYE.sample_surface(10, 20, z_max=0.0))
    with RunLogger(tmp_path / "m.mcap", metadata={"scenario": "toy", "seed": 3}) as log:
        log.log_model_update(0.5, update)
    (_, m), = read_log(tmp_path / "m.mcap").messages["/model"]
    assert (m["kind"], m["kind_index"], m["n_points"]) == ("sphere", 1, 200)
    assert m["sphere"]["radius"] == pytest.approx(12.0, abs=1e-9)
    assert set(m["criteria"]) == set(update.criteria) and all(set(c) == {"value", "met"} for c in m["criteria"].values())
    with open(tmp_path / "m.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["run"] == {"scenario": "toy", "seed": "3"} and set(meta["time"]) == {"start_time_ns", "log_time"}


def test_bad_arguments_are_refused_by_name(tmp_path):
    with RunLogger(tmp_path / "bad.mcap") as log:
        with pytest.raises(ValueError, match="t_s"):
            log.log_distance(-1.0, 5.0, True, 1.0)
        with pytest.raises(ValueError, match="t_s"):
            log.log_distance(float("nan"), 5.0, True, 1.0)
        with pytest.raises(ValueError, match="kind"):
            log.log_model(0.0, "cube")
        with pytest.raises(ValueError, match=r"X_W\['T'\]"):
            log.log_frames(0.0, {"T": np.eye(3)})
        with pytest.raises(ValueError, match="q, qdot and names"):
            log.log_joint_states(0.0, [0.0, 1.0], [0.0], ["a", "b"])
        x = toy_inputs([0.0, 0.0, -5.0], [1.0, 0.0, 0.0], 0.0, model=make_unloggable_model())
        with pytest.raises(ValueError, match="FilterInputs.model"):
            log.log_filter_step(x, SafetyFilter()(toy_inputs([0.0, 0.0, -5.0], [1.0, 0.0, 0.0], 0.0)))
    with pytest.raises(ValueError, match="flush_every_s"):
        RunLogger(tmp_path / "bad2.mcap", flush_every_s=0.0)


def make_unloggable_model():
    """A model the filter accepts (it answers signed_distance and gradient) but the log
    cannot rebuild: refused at logging time rather than making an unreplayable log."""

    class Plane:
        def signed_distance(self, Q):
            return 12.0 + np.atleast_2d(Q)[:, 2]

        def gradient(self, Q):
            return np.tile([0.0, 0.0, 1.0], (len(np.atleast_2d(Q)), 1))

    return Plane()


@pytest.mark.parametrize("wall_flush_at_step", [None, 1986])
def test_an_open_log_is_readable_up_to_the_last_second(tmp_path, monkeypatch, wall_flush_at_step):
    """Without closing (the writer still holds the file), every step up to the last whole
    second of simulation time is on disk, also when a second of wall time passed (and the
    writer flushed) a few steps before that second: the wall clock is frozen but for one
    jump of 1.5 s before step 1986."""
    wall = [0.0]
    monkeypatch.setattr(writer_module, "time", SimpleNamespace(monotonic=lambda: wall[0], time_ns=time.time_ns))
    filt, p = SafetyFilter(), np.array([0.0, 0.0, -10.0])
    log = RunLogger(tmp_path / "open.mcap", flush_every_s=1.0)
    for k in range(2500):
        if k == wall_flush_at_step:
            wall[0] += 1.5
        p = toy_step(log, filt, k, p)
    partial = read_log(tmp_path / "open.mcap", allow_truncated=True)
    assert partial.truncated
    last_t = partial.messages["/filter/inputs"][-1][1]["t"]
    assert last_t >= 2.0 - DT  # the step that crossed 2 s of simulation time flushed
    log.close()
    assert not read_log(tmp_path / "open.mcap").truncated


_CHILD = """
import sys, numpy as np
sys.path[:0] = [{root!r}, {here!r}]
from test_mcap_log import toy_step
from eval.log.writer import RunLogger
from safety import SafetyFilter
filt, p = SafetyFilter(), np.array([0.0, 0.0, -10.0])
log = RunLogger({path!r})
k = 0
while True:
    p = toy_step(log, filt, k, p)
    print(k, flush=True)
    k += 1
"""


def test_a_killed_writer_leaves_a_readable_log(tmp_path):
    """SIGKILL mid-run (no close, no summary): the log streams up to the last second."""
    path = tmp_path / "killed.mcap"
    root = str(Path(__file__).resolve().parents[2])
    child = subprocess.Popen([sys.executable, "-c", _CHILD.format(root=root, here=str(Path(__file__).parent), path=str(path))],
                             stdout=subprocess.PIPE, text=True, cwd=root)
    last, deadline = -1, time.monotonic() + 60.0
    try:
        for line in child.stdout:  # let it run 2.5 s of simulation time
            last = int(line)
            if last >= 2500 or time.monotonic() > deadline:
                break
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
    assert last >= 2500, "the writer did not get far enough"
    # steps after `last` may also have been logged before the kill landed
    log = read_log(path, allow_truncated=True)
    assert log.truncated
    steps = [m["step"] for _, m in log.messages["/filter/inputs"]]
    assert steps == list(range(len(steps)))
    assert steps[-1] * DT >= last * DT - 1.0  # at most a second of simulation time lost
    assert log.count("/filter/config") == 1 and log.count("/scene") >= steps[-1] // 10
