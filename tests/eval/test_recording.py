"""Recordings: a bag written with rosbags by hand is read and fitted; record -> fit with
an STL ground truth; bad input refused in one line, exit 2, nothing written."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from eval.cli import main
from eval.recording.bag import typestore

FULL_SCALE = 1000.0  # the default engine's 60 dB over the noise RMS


def _write_bag(path, joints, ascans, storage="sqlite3", joint_topic="/robot/joints", ascan_topic="/iioct/scan",
               names=("joint_6", "joint_5", "joint_4", "joint_3", "joint_2", "joint_1")):
    """A bag written with rosbags directly: joints [(t, q (6,))] as JointState with the
    names in `names` order (positions permuted to match), ascans [(t, amplitude (n,))] as
    32FC1 one-row Images."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    order = [int(n[-1]) - 1 for n in names]
    events = [(t, 0, q) for t, q in joints] + [(t, 1, a) for t, a in (ascans or [])]
    with Writer(path, version=9, storage_plugin=plugin) as w:
        cj = w.add_connection(joint_topic, "sensor_msgs/msg/JointState", typestore=store)
        ca = w.add_connection(ascan_topic, "sensor_msgs/msg/Image", typestore=store) if ascans is not None else None
        for t, kind, data in sorted(events, key=lambda e: e[0]):
            ns = int(round(t * 1e9))
            h = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="x")
            if kind == 0:
                msg = T["sensor_msgs/msg/JointState"](header=h, name=list(names), position=np.asarray(data)[order],
                                                      velocity=np.empty(0), effort=np.empty(0))
                w.write(cj, ns, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            else:
                raw = np.asarray(data, dtype="<f4").view(np.uint8)
                msg = T["sensor_msgs/msg/Image"](header=h, height=1, width=len(data), encoding="32FC1", is_bigendian=0,
                                                 step=4 * len(data), data=raw)
                w.write(ca, ns, store.serialize_cdr(msg, "sensor_msgs/msg/Image"))


@pytest.mark.slow
def test_a_bag_written_with_rosbags_directly_is_read_and_synchronised(tmp_path):
    """Not `record`'s bag: SQLite3 storage, other topic names, joints named in reverse
    order, float A-scans. The offset comes back within the 0.5 ms target."""
    from eval.recording.simulate import RecordingSpec, scenario_of, true_motion
    from models.iioct import synthesize_ascan
    from planning import Robot
    from planning.iioct import IioctSensor

    spec = RecordingSpec(shape="myopic", revolutions=1.0, pitch_mm=9.0, sync_s=1.5)
    scenario = scenario_of(spec)
    robot = Robot(scenario)
    motion = true_motion(robot, scenario, spec)
    keep = motion.t <= motion.sync_end_s + 0.6  # the synchronisation and a little of the scan
    t, Q = motion.t[keep], motion.q[keep]
    rng = np.random.default_rng(0)
    offset_s = -0.0062
    T = np.arange(0.0, t[-1], 5e-4)
    Qt = np.column_stack([np.interp(T, t, Q[:, i]) for i in range(6)])
    d, inc = IioctSensor(robot, mode="ascan").true_geometry(Qt)
    scans = [synthesize_ascan(di, ai, rng) for di, ai in zip(d, inc)]
    bag = tmp_path / "handmade"
    _write_bag(bag, list(zip(t, Q + 2e-5 * rng.standard_normal(Q.shape))), list(zip(T + offset_s, scans)))
    out = tmp_path / "fit"
    assert main(["fit", "--recording", str(bag), "--out", str(out)]) == 0
    r = json.loads((out / "fit.json").read_text())
    assert abs(r["time_offset_ms"] - 1e3 * offset_s) < 0.5
    assert r["sync"]["gain"] == pytest.approx(-1.0, abs=0.05) and r["n_points"] > 100
    # the extraction in worker processes gives every A-scan's distance exactly as in one
    from eval.recording.fit import read_recording

    one, two = read_recording(bag, jobs=1)[1], read_recording(bag, jobs=2)[1]
    np.testing.assert_array_equal(one.distance_mm, two.distance_mm)
    np.testing.assert_array_equal(one.confidence, two.confidence)


@pytest.mark.slow
def test_record_then_fit_with_the_printed_phantom(tmp_path):
    rec, stl, out = tmp_path / "rec", tmp_path / "stl", tmp_path / "fit"
    assert main(["record", "--out", str(rec), "--shape", "myopic", "--time-offset-ms", "7.5", "--revolutions", "3",
                 "--sync-s", "1.5", "--seed", "2"]) == 0
    truth = json.loads((rec / "truth.json").read_text())
    assert truth["time_offset_ms"] == 7.5 and "R_WE" in truth and not (rec / "recording" / "truth.json").exists()
    assert main(["eyes", "--stl", str(stl), "--edge-mm", "0.5"]) == 0
    assert main(["fit", "--recording", str(rec / "recording"), "--out", str(out),
                 "--ground-truth", str(stl / "myopic.stl")]) == 0
    r = json.loads((out / "fit.json").read_text())
    assert {"time_offset_ms", "kind", "n_points", "sf_fmae_um", "ef_fmae_um", "lf_fmae_um", "mae_um", "lf_mae_um",
            "registration_rmse_um"} <= set(r)
    assert abs(r["time_offset_ms"] - 7.5) < 0.5
    # a 3-turn spiral's model on the printed half: the closed loop's spread for 3 turns is
    # 39-57 um on the whole retina (test_cmd_sensor); the registration leaves the noise
    assert r["mae_um"] < 60.0 and r["registration_rmse_um"] < 40.0
    # the local-global model fits the same points at least as closely as the quadric (it is
    # the quadric plus a correction fitted to them)
    assert r["lf_fmae_um"] <= 1.05 * r[{"ellipsoid": "ef_fmae_um", "sphere": "sf_fmae_um"}[r["kind"]]]
    # the round trip (bag, clock offset and its estimate, extraction, fit) against the same
    # scan through the loop's sensor and model without it: at the true placement within
    # the target's 20 %
    from dataclasses import fields

    from eval.recording.ground_truth import load_stl, placed_mae_um
    from eval.recording.simulate import RecordingSpec, direct_model
    from models import Ellipsoid, Sphere

    spec = RecordingSpec(**{f.name: truth[f.name] for f in fields(RecordingSpec)})
    m = r["model"]
    fitted = (Ellipsoid(m["center_mm"], m["radii_mm"], m["rotation"]) if "radii_mm" in m
              else Sphere(m["center_mm"], m["radius_mm"]))
    mesh = load_stl(stl / "myopic.stl")
    reference = placed_mae_um(*mesh, direct_model(spec).shape, truth["R_WE"], truth["p_WE_mm"])
    assert placed_mae_um(*mesh, fitted, truth["R_WE"], truth["p_WE_mm"]) == pytest.approx(reference, rel=0.2)
    assert (out / "sync.png").exists() and (out / "fit.png").exists()
    # --no-bias-removal: the points registered as extracted (an OCT engine unlike the
    # simulated one whose bias the registration tabulates); the same fit, another placement
    assert r["registration"]["bias_removed"] is True
    plain = tmp_path / "fit_plain"
    assert main(["fit", "--recording", str(rec / "recording"), "--out", str(plain), "--ground-truth",
                 str(stl / "myopic.stl"), "--no-bias-removal"]) == 0
    r2 = json.loads((plain / "fit.json").read_text())
    assert r2["registration"]["bias_removed"] is False and r2["ef_fmae_um"] == r["ef_fmae_um"]
    assert r2["mae_um"] < 60.0 and r2["registration_rmse_um"] < 40.0


def _refused(capsys, argv, out, match):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and match in err, err
    assert not out.exists()


def test_a_file_that_is_not_a_bag_is_refused(tmp_path, capsys):
    f = tmp_path / "notes.mcap"
    f.write_text("not a bag\n")
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(f), "--out", str(out)], out, "not a readable ROS 2 bag")


def test_a_bag_without_the_ascans_is_refused(tmp_path, capsys):
    bag = tmp_path / "bag"
    _write_bag(bag, [(0.001 * k, np.zeros(6)) for k in range(10)], None)
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(bag), "--out", str(out)], out, "no sensor_msgs/msg/Image topic")


def test_a_bag_without_the_synchronisation_motion_is_refused(tmp_path, capsys):
    bag = tmp_path / "bag"
    noise = np.random.default_rng(0).rayleigh(0.7, 4096)
    _write_bag(bag, [(0.001 * k, np.full(6, 0.1)) for k in range(500)], [(0.0005 * k, noise) for k in range(20)])
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(bag), "--out", str(out)], out, "no synchronisation segment")


def test_joint_angles_in_degrees_are_refused(tmp_path, capsys):
    bag = tmp_path / "bag"
    _write_bag(bag, [(0.001 * k, np.full(6, 30.0)) for k in range(10)], [(0.0, np.ones(4096))])
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(bag), "--out", str(out)], out, "not radians")


@pytest.fixture(scope="module")
def phantom():
    from models.eyes import make_eye
    from models.eyes.mesh import lower_half_shell

    return lower_half_shell(make_eye("emmetropic"), edge_mm=1.0)


@pytest.mark.parametrize("defect, match", [("open", "not watertight"), ("metres", "metres?")])
def test_a_bad_stl_is_refused_before_any_work(tmp_path, capsys, phantom, defect, match):
    V, F = phantom
    mesh = trimesh.Trimesh(V * (1e-3 if defect == "metres" else 1.0), F[:-5] if defect == "open" else F, process=False)
    stl = tmp_path / "eye.stl"
    mesh.export(stl)
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(tmp_path / "missing"), "--out", str(out), "--ground-truth", str(stl)],
             out, match)


def test_record_refuses_bad_flags_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "rec"
    _refused(capsys, ["record", "--out", str(out), "--time-offset-ms", "150"], out, "--time-offset-ms")
    _refused(capsys, ["record", "--out", str(out), "--shape", "myopic", "--eye-param", "height_mm=3"], out, "height_mm")
    _refused(capsys, ["record", "--out", str(out), "--scan", "bench"], out, "unknown scan 'bench'; choose from surgery, phantom")


def test_a_csv_pair_with_extracted_distances_is_fitted(tmp_path):
    """joints.csv + oct.csv (distances the rig extracted): the offset within 0.5 ms."""
    from eval.recording.simulate import RecordingSpec, scenario_of, true_motion
    from planning import Robot
    from planning.iioct import IioctSensor

    spec = RecordingSpec(shape="hyperopic", revolutions=1.0, pitch_mm=9.0, sync_s=2.0)
    scenario = scenario_of(spec)
    robot = Robot(scenario)
    motion = true_motion(robot, scenario, spec)
    rng = np.random.default_rng(1)
    T = np.arange(0.0, motion.t[-1], 5e-4)
    Qt = np.column_stack([np.interp(T, motion.t, motion.q[:, i]) for i in range(6)])
    d = IioctSensor(robot, mode="ascan").true_geometry(Qt)[0] + 0.01 * rng.standard_normal(len(T))
    folder = tmp_path / "csv"
    folder.mkdir()
    q = motion.q + 2e-5 * rng.standard_normal(motion.q.shape)
    np.savetxt(folder / "joints.csv", np.column_stack([motion.t, q]), delimiter=",", comments="",
               header="t_s," + ",".join(f"q{k}_rad" for k in range(1, 7)))
    np.savetxt(folder / "oct.csv", np.column_stack([T + 0.0088, d]), delimiter=",", comments="", header="t_s,distance_mm")
    out = tmp_path / "fit"
    assert main(["fit", "--recording", str(folder), "--out", str(out)]) == 0
    r = json.loads((out / "fit.json").read_text())
    assert abs(r["time_offset_ms"] - 8.8) < 0.5 and r["kind"] in ("sphere", "ellipsoid")


def test_a_csv_pair_in_degrees_is_refused(tmp_path, capsys):
    folder = tmp_path / "csv"
    folder.mkdir()
    (folder / "joints.csv").write_text("t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n0,1,2,3,4,5,6\n")
    (folder / "oct.csv").write_text("t_s,distance_mm\n0,10\n")
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(folder), "--out", str(out)], out, "q1_rad")


@pytest.mark.parametrize("content, match", [('{"p_FS_mm": [0.092, 0, 0], "u_F": [1, 0, 0]}', "not in mm"),
                                            ('{"shape": "myopic"}', "not a calibration JSON")])
def test_a_bad_calibration_is_refused_before_any_work(tmp_path, capsys, content, match):
    cal = tmp_path / "calibration.json"
    cal.write_text(content)
    out = tmp_path / "out"
    _refused(capsys, ["fit", "--recording", str(tmp_path / "missing"), "--out", str(out), "--calibration", str(cal)],
             out, match)


def test_sensor_displacements_are_how_a_lateral_calibration_error_moves_each_point():
    """eval.recording.fit.sensor_displacements against the beams of a sensor pose off by a
    known error (0.02 and -0.01 mm across the beam, 0.1 and -0.05 deg of tilt): the point at
    each distance moves by the displacements times the error, to the second order's
    d x tilt^2 (15 mm x (2e-3 rad)^2 = 0.06 um)."""
    from scipy.spatial.transform import Rotation

    from eval.cli.calibrate import nominal_sensor
    from eval.recording.fit import beams_W, sensor_displacements, sensor_frame
    from models.calibration.plate import SensorPose

    rng = np.random.default_rng(4)
    Q = rng.uniform(-0.4, 0.4, (50, 6))
    d = rng.uniform(3.0, 15.0, 50)
    nominal = nominal_sensor()
    R_FS = sensor_frame(nominal.u_F)
    xi = np.array([0.02, -0.01, np.radians(0.1), np.radians(-0.05)])
    true = SensorPose(nominal.p_FS + R_FS[:, :2] @ xi[:2], R_FS @ Rotation.from_rotvec([xi[2], xi[3], 0.0]).apply([0, 0, 1.0]))
    (O, U), (O_t, U_t) = beams_W(nominal, Q), beams_W(true, Q)
    moved = (O_t + d[:, None] * U_t) - (O + d[:, None] * U)
    assert np.abs(moved).max() > 0.02  # the error moves the points by tens of um
    assert np.allclose(sensor_displacements(nominal, Q, d) @ xi, moved, atol=1e-4)
