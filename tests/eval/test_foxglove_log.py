"""A closed-loop log shows the run in Foxglove's 3D panel: the robot's links (scene
entities locked to link frames that move with the joints), the measured retinal points
(foxglove.PointCloud), the model and the boundary it keeps, filter stops as foxglove.Log;
every message decoded with Foxglove's published schemas (foxglove-sdk's)."""
from __future__ import annotations

import numpy as np
import pytest
from test_closed_loop import deep_start, model_from_spiral_beams
from test_mcap_log import decode_foxglove

from eval.closed_loop import ClosedLoop, LoopConfig
from eval.experiments.command_sources import VelocityReplayCommand
from eval.log.writer import RunLogger, read_log
from eval.systems.model import MODEL_LOG_PERIOD_S
from planning import SurgeryScenario

ARM_LINKS = {"base", "link1", "link2", "link3", "link4", "link5", "flange", "instrument"}  # meca500.urdf's visuals
START_NS = 1_800_000_000_000_000_000  # the run's wall-clock start


@pytest.fixture(scope="module")
def run_log(tmp_path_factory):
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario)
    loop = ClosedLoop(scenario, LoopConfig())
    n_before = model.n_points
    # 5 mm/s toward the back of the eye for 0.15 s, then an absurd 1 m/s command: the filter stops the robot
    source = VelocityReplayCommand([0.0, 0.15], [[3.0, 0.0, -4.0], [1000.0, 0.0, 0.0]])
    path = tmp_path_factory.mktemp("fox") / "run.mcap"
    with RunLogger(path, loop.config.filter, start_ns=START_NS) as log:
        run = loop.run(source, deep_start(loop), 0.3, model=model, coverage=coverage, logger=log)
    return read_log(path), run, model, n_before, loop


def _scenes(log):
    return [(t, decode_foxglove("/scene", m)) for t, m in log.messages["/scene"]]


def test_the_robot_links_are_scene_entities_locked_to_frames_that_move(run_log):
    log, run, _, _, _ = run_log
    scenes = _scenes(log)
    entities = {e.id: e for e in scenes[0][1].entities}
    robot = {i[len("robot/"):]: e for i, e in entities.items() if i.startswith("robot/")}
    assert set(robot) == ARM_LINKS
    assert all(e.frame_locked and e.frame_id == name for name, e in robot.items())
    shaft = min(robot["instrument"].cylinders, key=lambda c: c.size.x)
    assert shaft.size.x == pytest.approx(0.5e-3) and shaft.size.z == pytest.approx(0.032)  # 25G, 32 mm, in metres
    tfs = [decode_foxglove("/tf", m) for _, m in log.messages["/tf"]]
    frames = {t.child_frame_id for t in tfs[0].transforms}
    assert ARM_LINKS <= frames and all(t.parent_frame_id == "W" for t in tfs[0].transforms)
    instrument = [next(t for t in tf.transforms if t.child_frame_id == "instrument") for tf in tfs]
    moved_m = np.linalg.norm([getattr(instrument[-1].translation, a) - getattr(instrument[0].translation, a) for a in "xyz"])
    assert moved_m > 1e-4  # the robot moved the instrument (5 mm/s for 0.15 s: up to 0.75 mm)


def test_the_measured_points_accumulate_as_point_clouds(run_log):
    log, run, model, n_before, loop = run_log
    clouds = [decode_foxglove("/oct/points", m) for _, m in log.messages["/oct/points"]]
    # the points gathered over each MODEL_LOG_PERIOD_S of simulation time (packets every 10 ms)
    assert len(clouds) >= int((run.t[-1] - run.t[0]) / MODEL_LOG_PERIOD_S)
    P = np.concatenate([np.frombuffer(c.data, dtype="<f4").reshape(-1, 3) for c in clouds]).astype(float) * 1e3
    assert all(c.frame_id == "W" and c.point_stride == 12 and [f.name for f in c.fields] == ["x", "y", "z"] for c in clouds)
    assert len(P) == model.n_points - n_before  # every point the model took in during the run, once
    # measured retina: within the sensor's noise (20 um SD) and float32 rounding of the true retina
    assert np.max(np.abs(loop.scenario.eye.signed_distance(P))) < 0.15


def test_the_model_and_its_boundary_are_in_the_scene(run_log):
    log, _, _, _, loop = run_log
    for _, scene in _scenes(log):
        entities = {e.id: e for e in scene.entities}
        eye, boundary = entities["eye_model"].spheres[0], entities["boundary"].spheres[0]
        keep_m = 1e-3 * loop.config.filter.d_safe_mm
        assert eye.size.x - boundary.size.x >= 2 * keep_m - 1e-12  # the boundary lies d_safe + margin inside
    assert log.count("/filter/models") >= 1


def test_a_filter_stop_is_a_foxglove_log_message_at_its_time(run_log):
    log, run, _, _, _ = run_log
    events = [(t, decode_foxglove("/log", m)) for t, m in log.messages["/log"]]
    stops = [(t, e) for t, e in events if e.message.startswith("filter stop:")]
    assert stops and stops[0][1].level == 3  # foxglove.LogLevel WARNING
    first_fault = run.t[np.flatnonzero(~run.ok)[0]]
    assert stops[0][0] - START_NS == pytest.approx(first_fault * 1e9, abs=1.0)  # log time = start + simulation time
    assert stops[0][1].timestamp.seconds * 10**9 + stops[0][1].timestamp.nanos == stops[0][0]
