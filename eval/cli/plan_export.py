"""The multi-port plan's joint trajectory for a real controller, and its coverage map.

- `plan_pieces`: the plan in execution order as (port, phase, joint trajectory, window)
  pieces: per pass enter, insert, sweep, withdraw, exit (planning.multiport.PortSegment.pieces);
  between passes the move.
- `write_trajectory_csv`: time (s), active port, phase, six joint angles (rad) and
  velocities (rad/s), sampled every CSV_DT_S.
- `write_ros2_trajectories`: one ROS 2 trajectory_msgs/msg/JointTrajectory per port
  pass (enter, insert, sweep, withdraw, exit; time_from_start from the pass's start) on
  TRAJECTORY_TOPIC, in a rosbag2 with MCAP storage (rosbags, Apache-2.0: rosbag2's own
  layout and CDR serialisation, which a hand-written writer would have to re-create).
- `coverage_figure`: the band unrolled (azimuth x height), each cell coloured by the
  port that swept it or the reason it could not be reached.
Units: s, rad; frame W.
"""
from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np

CSV_DT_S = 0.01
ROS_DT_S = 0.02
TRAJECTORY_TOPIC = "/vitreoguard/plan/joint_trajectory"
JOINT_NAMES = tuple(f"meca500_joint{k}" for k in range(1, 7))
PORT_COLORS = ("tab:green", "tab:cyan", "tab:olive", "tab:pink")
REASON_COLORS = {"uncertain": "gold", "lens": "tab:blue", "port": "tab:orange", "reach": "tab:red", "shaft": "tab:purple",
                 "depression": "tab:brown", "declined": "tab:gray"}


def plan_pieces(plan) -> list[tuple[str, str, object, float, float]]:
    """[(port or "a->b", phase, trajectory, t0 s, t1 s)] in execution order: each pass's
    enter, insert, sweep, withdraw, exit (PortSegment.pieces) and the move between passes,
    each the trajectory's window [t0, t1]; pieces without duration left out."""
    pieces = []
    for k, seg in enumerate(plan.segments):
        if k:
            sw, move = plan.switches[k - 1], plan.moves[k - 1]
            pieces.append((f"{sw.from_port}->{sw.to_port}", "move", move, move.start_time(), move.end_time()))
        pieces += [(seg.port.name, phase, traj, a, b) for phase, traj, a, b in seg.pieces() if b - a > 1e-9]
    return pieces


def _sampled(traj, t0: float, t1: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times from t0 (K,), q (K, 6), qdot (K, 6)) on [t0, t1] every dt, t1 included (a
    sample of the grid closer than dt / 2 to t1 left out: it would print as t1 itself)."""
    ts = np.append(np.arange(t0, t1 - 0.5 * dt, dt), t1) if t1 - t0 > 0.5 * dt else np.array([t0, t1])
    Q = traj.vector_values(ts).T
    dQ = traj.derivative(1).vector_values(ts).T
    return ts - t0, Q, dQ


def write_trajectory_csv(plan, path) -> Path:
    """plan_trajectory.csv: t_s, port, phase, q1..q6 rad, qdot1..qdot6 rad/s."""
    path = Path(path)
    tmp = path.with_suffix(".csv.part")
    t_start = 0.0
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "port", "phase"] + [f"q{k}_rad" for k in range(1, 7)] + [f"qdot{k}_rad_s" for k in range(1, 7)])
        for port, phase, traj, a, b in plan_pieces(plan):
            ts, Q, dQ = _sampled(traj, a, b, CSV_DT_S)
            for t, q, dq in zip(ts[:-1] if len(ts) > 1 else ts, Q, dQ):
                w.writerow([f"{t_start + t:.4f}", port, phase] + [f"{v:.7f}" for v in q] + [f"{v:.7f}" for v in dq])
            t_start += ts[-1]
    tmp.replace(path)
    return path


def write_ros2_trajectories(plan, path, start_ns: int) -> Path:
    """A rosbag2 directory `path` (MCAP storage) with one JointTrajectory per port segment,
    stamped at the segment's planned start (start_ns + plan time, ns since the epoch)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Duration, Time, Header = T["builtin_interfaces/msg/Duration"], T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Traj, Point = T["trajectory_msgs/msg/JointTrajectory"], T["trajectory_msgs/msg/JointTrajectoryPoint"]
    path = Path(path)
    if path.exists():
        shutil.rmtree(path)
    pieces = plan_pieces(plan)
    t_plan = 0.0
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(TRAJECTORY_TOPIC, Traj.__msgtype__, typestore=ts)
        k = 0
        while k < len(pieces):
            if pieces[k][1] == "move":
                t_plan += pieces[k][4] - pieces[k][3]
                k += 1
                continue
            port, points, t_seg = pieces[k][0], [], 0.0
            n = next((j for j in range(k, len(pieces)) if pieces[j][1] == "move"), len(pieces)) - k
            for _, _, traj, a, b in pieces[k:k + n]:  # the pass: enter, insert, sweep, withdraw, exit
                times, Q, dQ = _sampled(traj, a, b, ROS_DT_S)
                for t, q, dq in zip(times, Q, dQ):
                    if points and t == 0.0:
                        continue  # a piece starts where the last ended
                    s = t_seg + t
                    points.append(Point(positions=q.astype(float), velocities=dq.astype(float), accelerations=np.zeros(0),
                                        effort=np.zeros(0), time_from_start=Duration(sec=int(s), nanosec=int(round((s % 1) * 1e9)) % 1_000_000_000)))
                t_seg += times[-1]
            stamp = start_ns + int(round(t_plan * 1e9))
            msg = Traj(header=Header(stamp=Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000), frame_id=f"trocar_{port}"),
                       joint_names=list(JOINT_NAMES), points=points)
            writer.write(conn, stamp, ts.serialize_cdr(msg, Traj.__msgtype__))
            t_plan += t_seg
            k += n
    return path


def coverage_figure(plan, swept: np.ndarray, title: str):
    """The band unrolled: each cell coloured by the port that swept it (`swept` (n_rings,
    n_az) bool: the executed cutter port passed it) or the reason it was not reached;
    cells planned but missed in execution hatched."""
    import matplotlib.pyplot as plt

    band = plan.band
    fig, ax = plt.subplots(figsize=(11, 4))
    A, Z = np.meshgrid(np.degrees(band.azimuth), band.z_E)
    for k, port in enumerate(plan.ports):
        m = (plan.port_of == k) & swept
        if m.any():
            ax.scatter(A[m], Z[m], s=30, marker="s", color=PORT_COLORS[k % len(PORT_COLORS)],
                       label=f"{port.name} ({port.clock_hour:g} o'clock): {int(m.sum())}")
    missed = (plan.port_of >= 0) & ~swept
    if missed.any():
        ax.scatter(A[missed], Z[missed], s=30, marker="x", color="k", label=f"planned, not swept: {int(missed.sum())}")
    for reason, color in REASON_COLORS.items():
        m = (plan.port_of < 0) & (band.reason == reason)
        if m.any():
            ax.scatter(A[m], Z[m], s=30, marker="s", color=color, alpha=0.55, label=f"{reason}: {int(m.sum())}")
    for port in plan.ports:
        az = np.degrees(port.azimuth_rad) % 360.0
        ax.axvline(az, color="0.3", lw=0.8, ls="--")
        ax.text(az, band.z_E[-1] + 0.35, port.name, ha="center", fontsize=7)
    ax.set_xlim(-5, 365)
    ax.set_ylim(band.z_E[0] - 0.5, band.z_E[-1] + 0.8)
    ax.set_xlabel("azimuth in the eye frame (deg from +x_E towards +y_E; 12 o'clock = 90)")
    ax.set_ylabel("height z_E (mm): equator 0, ora serrata 5")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="lower center", ncol=4, bbox_to_anchor=(0.5, -0.42))
    fig.tight_layout()
    return fig
