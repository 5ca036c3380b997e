"""`vitreoguard plan`: the JSON contract on a reduced band (plan only), the trajectory
exports, bad input."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from eval.cli import main

KEYS = {"band_coverage", "band_coverage_planned", "planned_cells", "planned_cells_swept", "cells", "ports",
        "port_switches", "reentries", "switches", "unreachable", "min_model_clearance_mm", "min_true_clearance_mm",
        "violations", "duration_s", "path_length_mm", "min_joint_margin_deg", "filter_intervention_fraction",
        "plan_time_s", "outside_loop_s", "min_joint_margin_deg_outside_loop"}


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    out = tmp_path_factory.mktemp("plan") / "plan"
    assert main(["plan", "--out", str(out), "--band", "0,2", "--no-execute"]) == 0
    return out, json.loads((out / "plan.json").read_text())


def test_plan_writes_the_contract(planned):
    out, r = planned
    assert KEYS <= set(r) and "coverage" not in r  # the band's figure has one name
    # rings 0, 1, 2 mm, each of ceil(2 pi r) cells of 1 mm, r the fitted model's equatorial radius: the true
    # 11.455 mm (71.97 mm round) give 72, the fit within 65 um of it (2 pi x 0.065 = 0.41 mm) 72 or 73
    assert r["cells"] in (3 * 72, 3 * 73)
    assert sum(r["unreachable"].values()) + r["planned_cells"] == r["cells"]
    assert sum(p["cells_assigned"] for p in r["ports"].values()) == r["planned_cells"]
    assert set(r["ports"]) == {"superonasal", "superotemporal"}  # the working ports; infusion only when asked for
    assert r["ports"]["superonasal"]["clock_hour"] == 2 and r["ports"]["superotemporal"]["clock_hour"] == 10  # right eye
    assert r["band_coverage_planned"] >= 0.9 * r["planned_cells"] / r["cells"]
    assert r["port_switches"] == 1  # each working port visited once
    assert len(r["switches"]) == r["port_switches"] + r["reentries"]
    assert all(s["move_min_outside_mm"] > 0 and s["duration_s"] > 0 for s in r["switches"])
    assert r["min_model_clearance_mm"] >= 0.95  # 1 mm standoff, spline within 50 um of the targets
    assert r["min_joint_margin_deg"] >= 4.5  # 5 deg at the waypoints; the spline between them within 0.5
    assert r["min_joint_margin_deg_outside_loop"] >= 2.0 - 1e-6  # the filter's joint margin, on the way in, out and between
    assert r["min_true_clearance_mm"] is None and r["filter_intervention_fraction"] is None  # not executed
    assert (out / "coverage.png").stat().st_size > 10_000


def test_the_trajectory_csv_is_continuous_and_within_the_speed_limits(planned):
    from planning.robot import Robot

    out, r = planned
    with open(out / "plan_trajectory.csv") as f:
        rows = list(csv.DictReader(f))
    t = np.array([float(x["t_s"]) for x in rows])
    Q = np.array([[float(x[f"q{k}_rad"]) for k in range(1, 7)] for x in rows])
    dQ = np.array([[float(x[f"qdot{k}_rad_s"]) for k in range(1, 7)] for x in rows])
    assert np.all(np.diff(t) > 0)
    assert {x["port"] for x in rows if x["phase"] == "sweep"} == {"superonasal", "superotemporal"}
    robot = Robot()
    assert np.all(np.abs(dQ) <= robot.qdot_max * 1.001)
    # no jump: a row's angles follow from the previous one's within what the speed limit allows
    assert np.all(np.abs(np.diff(Q, axis=0)) <= robot.qdot_max * np.diff(t)[:, None] * 1.01 + 1e-6)


def test_the_ros2_bag_holds_one_joint_trajectory_per_port_segment(planned):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    from eval.cli.plan_export import JOINT_NAMES, TRAJECTORY_TOPIC

    out, r = planned
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(out / "plan_trajectory") as reader:
        msgs = [ts.deserialize_cdr(raw, conn.msgtype) for conn, _, raw in reader.messages()
                if conn.topic == TRAJECTORY_TOPIC]
    assert len(msgs) == 1 + len(r["switches"])  # one per segment
    for m in msgs:
        assert tuple(m.joint_names) == JOINT_NAMES and len(m.points) > 10
        t = [p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in m.points]
        assert np.all(np.diff(t) > 0) and all(len(p.positions) == 6 for p in m.points)


@pytest.mark.parametrize("argv, message", [
    (["--standoff-mm", "0.4"], "--standoff-mm 0.4 is below the filter's boundary"), (["--band", "x"], "--band"),
    (["--band", "9,12"], "outside the model"), (["--shape", "egg"], "unknown shape"),
    (["--ports", "superonasal,nasal"], "unknown port 'nasal'"), (["--port-clock", "superonasal=13"], "[1, 12]"),
    (["--port-clock", "superonasal=0.5"], "[1, 12]"), (["--port-clock", "lateral=3"], "unknown port"),
    (["--port-limbus-mm", "2"], "--port-limbus-mm: must be a number in [3, 5] mm"), (["--port-limbus-mm", "6.5"], "[3, 5] mm"),
    (["--side", "middle"], "unknown eye side"), (["--survey-mm", "3.5"], "--survey-mm: must be a number in [0, 3] mm"),
    (["--survey-mm", "-1"], "--survey-mm"), (["--survey-passes", "0"], "--survey-passes: must be an integer in [1, 4]"),
    (["--survey-passes", "2"], "--survey-passes needs --survey-mm above 0 mm")])
def test_bad_plans_exit_2_and_write_nothing(argv, message, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["plan", "--out", str(out), "--no-execute", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) <= 2, err  # usage line + one line, no traceback
    assert not out.exists()


def test_an_ellipsoid_that_is_no_eye_gives_way_to_the_sphere_and_its_wider_boundary(tmp_path, capsys):
    """The pointed eye's ellipsoid (fitted to its posterior cap) has semi-axes of 150 and 29
    mm: the filter bounds the motion with the sphere fit instead, whose phase margin
    (1 mm) and the calibration bound (0.064 mm) put the boundary at 1.56 mm, so a 1 mm
    standoff is refused before any motion."""
    out = tmp_path / "never"
    assert main(["plan", "--shape", "pointed", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "below the boundary the filter keeps from this sphere model (1.564 mm)" in err and "at least 1.77 mm" in err
    assert not out.exists()


def test_with_the_local_model_the_plan_keeps_to_its_sigma(tmp_path):
    """`--model local`: the plan keeps to the filter's d_safe + 3 sigma. Far from the spiral's
    directions the emmetropic eye's sigma is the global ellipsoid's 0.3 mm (LocalConfig), so
    the band's 1 mm-standoff targets lie within 0.564 + 0.9 + 0.2 mm of the model: nearly
    every cell is "uncertain", none planned through a boundary the filter would hold (a cell
    is planned only where 3 sigma at its target, and beside it, is under about 0.1 mm: 15
    of 219 here); the least boundary is at least 0.564 mm + 3 x the 0.03 mm sigma floor."""
    out = tmp_path / "plan"
    assert main(["plan", "--out", str(out), "--band", "0,2", "--no-execute", "--model", "local"]) == 0
    r = json.loads((out / "plan.json").read_text())
    assert r["boundary_mm"] >= 0.564 + 3 * 0.03 - 1e-6
    assert r["unreachable"]["uncertain"] >= 0.85 * r["cells"]
    assert sum(r["unreachable"].values()) + r["planned_cells"] == r["cells"]
    cal = r["model"]["sigma_calibration"]  # the sd's calibration factors: at least 1, never falling with the gap
    assert cal["gap_deg"][0] == 0.0 and len(cal["gap_deg"]) == len(cal["factor"])
    assert all(f >= 1.0 for f in cal["factor"]) and all(b >= a for a, b in zip(cal["factor"], cal["factor"][1:]))
    # on the way through the spiral (a probe every 0.25 s of its ~33 s): the fits of a regular eye's first rings are
    # too small (a cap's), so wherever 3 sigma does not cover the retina the model lies inside it: no unsafe-side miss
    way = r["model"]["on_the_way"]
    assert way["probes"] >= 100 and 0.0 < way["lowest_sigma3_coverage"] <= r["model"]["sigma3_coverage"] == 1.0
    assert way["largest_unsafe_fraction"] == 0.0 and way["largest_unsafe_at_s"] is None and way["worst_excess_um"] < 0.0


def test_every_reason_a_cell_can_get_has_a_colour_in_the_coverage_map():
    from eval.cli.plan_export import REASON_COLORS
    from planning.multiport import UNREACHABLE

    assert set(REASON_COLORS) == set(UNREACHABLE)


def test_a_survey_sweeps_the_band_deeper_before_the_plan_is_made(tmp_path):
    """`--survey-mm 1 --survey-passes 2`: the band (rings 0 and 1 mm) is first swept twice
    1 mm deeper than the 2 mm standoff, filter on, through the closed loop against the true
    eye, the second pass planned on the model the first left; plan.json reports each pass
    (its cells, how much of the band it swept, its true clearance: the default boundary,
    0.5 mm, kept: 0 violations) and the survey as a whole (the last model's band swept by either pass, the
    interventions over both passes' steps) and the whole surgery (survey and shaving);
    each pass's log is written beside plan.json."""
    from mcap.reader import make_reader

    out = tmp_path / "plan"
    assert main(["plan", "--out", str(out), "--band", "0,1", "--standoff-mm", "2", "--survey-mm", "1",
                 "--survey-passes", "2"]) == 0
    r = json.loads((out / "plan.json").read_text())
    s = r["survey"]
    assert s["standoff_mm"] == pytest.approx(3.0) and len(s["passes"]) == 2
    for p in s["passes"]:
        assert p["planned_cells"] > 0.5 * r["cells"] and p["planned_cells_swept"] == 1.0
        assert p["band_coverage"] >= p["planned_cells"] / r["cells"] - 1e-9 and p["duration_s"] > 0
        assert p["violations"] == 0 and p["min_true_clearance_mm"] >= 0.5 and p["failsafe_stops"] == 0
        assert p["filter_intervention_fraction"] == pytest.approx(p["intervened_steps"] / p["steps"])
        assert p["sweep_true_depth_mm"]["median"] == pytest.approx(3.0, abs=0.15)  # the emmetropic model is exact
    assert s["band_coverage"] >= s["passes"][-1]["band_coverage"] - 1e-12  # the last model's band, by either pass
    assert s["planned_cells"] == s["passes"][-1]["planned_cells"]  # the last pass's plan
    assert s["planned_cells_swept"] == min(p["planned_cells_swept"] for p in s["passes"])
    assert s["steps"] == sum(p["steps"] for p in s["passes"])
    assert s["duration_s"] == pytest.approx(sum(p["duration_s"] for p in s["passes"]))
    assert s["min_true_clearance_mm"] == min(p["min_true_clearance_mm"] for p in s["passes"])
    for k in (1, 2):
        with open(out / f"survey_{k}.mcap", "rb") as f:
            assert sum(1 for _ in make_reader(f).iter_messages(topics=["/filter/step"])) > 0
    steps = s["steps"] + r["execution"]["steps"]  # the whole surgery: both survey passes and the shaving
    intervened = s["intervened_steps"] + r["filter_intervention_fraction"] * r["execution"]["steps"]
    assert r["filter_intervention_fraction_with_survey"] == pytest.approx(intervened / steps)
    assert r["min_true_clearance_mm_with_survey"] == min(s["min_true_clearance_mm"], r["min_true_clearance_mm"])
    assert r["sweep_true_depth_mm"]["median"] == pytest.approx(2.0, abs=0.15) and r["violations"] == 0