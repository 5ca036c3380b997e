"""A rig's recording as a ROS 2 bag (rosbag2, MCAP storage by default) or a CSV pair.

What a recording holds (any bag with these message types reads, whoever wrote it):
- the robot's joint angles: `sensor_msgs/msg/JointState` (default topic
  `/joint_states`), `position` the six joint angles J1..J6 in rad (in that order, or
  named `*1*`..`*6*`, e.g. meca_axis_1_joint..), `header.stamp` on the robot's clock;
- the iiOCT A-scans: `sensor_msgs/msg/Image` (default topic `/oct/ascan`), one row
  (height 1) of `width` = the engine's samples (4096), encoding `mono16` (detector
  counts, 65535 = the detector's full scale) or `32FC1` (amplitudes in noise-RMS units),
  `header.stamp` on the OCT's clock, one message per A-scan (2 kHz).
The CSV pair (a folder): `joints.csv` with a header `t_s,q1_rad,...,q6_rad`, and
`ascans.csv` with `t_s,a0,...,a4095` (amplitudes in noise-RMS units) or `oct.csv` with
`t_s,distance_mm` (distances the rig's software extracted already).

Reading never holds every A-scan: each is handed to `on_ascan` (the extractor) as it
is read. Units: s, rad, mm.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

JOINT_TOPIC = "/joint_states"
ASCAN_TOPIC = "/oct/ascan"
JOINT_NAMES = tuple(f"meca_axis_{k}_joint" for k in range(1, 7))
FULL_SCALE_COUNTS = 65535


class RecordingError(ValueError):
    """A recording that cannot be used (the message says what is missing or wrong)."""


def typestore():
    """rosbags' type store of ROS 2 Humble (sensor_msgs, std_msgs, trajectory_msgs ...)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


@dataclass(frozen=True)
class JointStream:
    """The robot's stream: stamps t_s (K,) s (robot clock, sorted) and joint angles q_rad (K, 6)."""

    t_s: np.ndarray
    q_rad: np.ndarray


@dataclass(frozen=True)
class OctStream:
    """The OCT stream after extraction: stamps t_s (N,) s (OCT clock, sorted), distances
    (N,) mm (NaN where invalid) and the extractor's confidences (N,); `extracted`: the
    distances come from the project's extractor (models.iioct), whose bias is tabulated
    (False: distances a rig extracted, an oct.csv)."""

    t_s: np.ndarray
    distance_mm: np.ndarray
    confidence: np.ndarray
    extracted: bool = True


class BagWriter:
    """Writes a recording bag (a rosbag2 folder `path`, which must not exist) with the
    joint and A-scan connections; messages in stamp order through `joints` and `ascans`."""

    def __init__(self, path, storage: str = "mcap", joint_topic: str = JOINT_TOPIC, ascan_topic: str = ASCAN_TOPIC):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.store = typestore()
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
        self._writer = Writer(Path(path), version=9, storage_plugin=plugin)
        self._writer.open()
        T = self.store.types
        self._joint = self._writer.add_connection(joint_topic, "sensor_msgs/msg/JointState", typestore=self.store)
        self._ascan = self._writer.add_connection(ascan_topic, "sensor_msgs/msg/Image", typestore=self.store)
        self._Header, self._Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
        self._JointState, self._Image = T["sensor_msgs/msg/JointState"], T["sensor_msgs/msg/Image"]

    def _header(self, t_s: float, frame: str):
        ns = int(round(t_s * 1e9))
        return self._Header(stamp=self._Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame), ns

    def joints(self, t_s: float, q_rad) -> None:
        header, ns = self._header(t_s, "meca500_base")
        msg = self._JointState(header=header, name=list(JOINT_NAMES), position=np.asarray(q_rad, dtype=np.float64),
                               velocity=np.empty(0), effort=np.empty(0))
        self._writer.write(self._joint, ns, self.store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))

    def ascan(self, t_s: float, counts: np.ndarray) -> None:
        """One A-scan (n,) uint16 detector counts (mono16, FULL_SCALE_COUNTS = full scale)."""
        header, ns = self._header(t_s, "iioct_fiber")
        data = np.ascontiguousarray(counts, dtype="<u2").view(np.uint8)
        msg = self._Image(header=header, height=1, width=len(counts), encoding="mono16", is_bigendian=0,
                          step=2 * len(counts), data=data)
        self._writer.write(self._ascan, ns, self.store.serialize_cdr(msg, "sensor_msgs/msg/Image"))

    def close(self) -> None:
        self._writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def counts_of(amplitude: np.ndarray, full_scale: float) -> np.ndarray:
    """Detector counts (uint16) of amplitudes in noise-RMS units, full_scale -> 65535."""
    return np.clip(np.rint(np.asarray(amplitude) * (FULL_SCALE_COUNTS / full_scale)), 0, FULL_SCALE_COUNTS).astype(np.uint16)


def _stamp_s(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def _joint_order(names) -> np.ndarray | None:
    """Indices of J1..J6 in a JointState's names (a name holding the digit k for Jk), or
    None to take the first six positions in order."""
    names = list(names)
    if len(names) < 6:
        return None
    order = []
    for k in "123456":
        hits = [i for i, n in enumerate(names) if k in n and not any(d in n for d in "123456".replace(k, ""))]
        if len(hits) != 1:
            return None
        order.append(hits[0])
    return np.array(order)


def _ascan_amplitude(msg, full_scale: float, n_samples: int) -> np.ndarray:
    """The A-scan of an Image message in noise-RMS units; RecordingError when it is no A-scan."""
    if msg.height != 1 or msg.width != n_samples:
        raise RecordingError(f"A-scan images must be 1 x {n_samples} (one A-scan of the OCT engine's {n_samples} samples), "
                             f"got {msg.height} x {msg.width}")
    raw = np.asarray(msg.data, dtype=np.uint8)
    if msg.encoding == "mono16":
        counts = raw.view(">u2" if msg.is_bigendian else "<u2")
        return counts.astype(np.float64) * (full_scale / FULL_SCALE_COUNTS)
    if msg.encoding == "32FC1":
        return raw.view(">f4" if msg.is_bigendian else "<f4").astype(np.float64)
    raise RecordingError(f"A-scan image encoding {msg.encoding!r} is not supported; use mono16 (detector counts, 65535 "
                         "= full scale) or 32FC1 (noise-RMS units)")


def _pick_topic(reader, msgtype: str, wanted: str | None, flag: str) -> list:
    conns = [c for c in reader.connections if c.msgtype == msgtype]
    if wanted is not None:
        conns = [c for c in conns if c.topic == wanted]
        if not conns:
            raise RecordingError(f"the bag has no {msgtype} topic {wanted!r} ({flag}); its topics: "
                                 + ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections))
        return conns
    topics = sorted({c.topic for c in conns})
    if not topics:
        raise RecordingError(f"the bag has no {msgtype} topic; its topics: "
                             + (", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections) or "none"))
    if len(topics) > 1:
        raise RecordingError(f"the bag has several {msgtype} topics ({', '.join(topics)}): choose one with {flag}")
    return conns


def read_bag(path, on_ascan, full_scale: float, n_samples: int, joint_topic: str | None = None,
             ascan_topic: str | None = None, progress=None) -> tuple[JointStream, np.ndarray]:
    """(the joint stream, the OCT stamps (N,) s) of the bag at `path` (a rosbag2 folder or
    an .mcap / .db3 file); each A-scan (noise-RMS units) goes to `on_ascan` in stamp
    order. `progress(n, total)`: called with the number of A-scans read so far and the
    bag's count of them, every 1000.
    RecordingError when the path is no bag or lacks the topics."""
    from rosbags.highlevel import AnyReader

    p = Path(path)
    try:
        reader = AnyReader([p], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises several types for files that are no bag
        raise RecordingError(f"--recording {p} is not a readable ROS 2 bag ({type(exc).__name__}: {exc})") from None
    try:
        jconns = _pick_topic(reader, "sensor_msgs/msg/JointState", joint_topic, "--joint-topic")
        aconns = _pick_topic(reader, "sensor_msgs/msg/Image", ascan_topic, "--ascan-topic")
        t_j, q_j, t_a, order = [], [], [], None
        total = sum(int(getattr(c, "msgcount", 0) or 0) for c in aconns)
        for conn, _, raw in reader.messages(connections=jconns + aconns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "sensor_msgs/msg/JointState":
                if order is None:
                    order = _joint_order(msg.name)
                pos = np.asarray(msg.position, dtype=float)
                if len(pos) < 6:
                    raise RecordingError(f"{conn.topic}: JointState with {len(pos)} positions; the Meca500 has 6")
                t_j.append(_stamp_s(msg.header))
                q_j.append(pos[order] if order is not None else pos[:6])
            else:
                t_a.append(_stamp_s(msg.header))
                on_ascan(_ascan_amplitude(msg, full_scale, n_samples))
                if progress is not None and len(t_a) % 1000 == 0:
                    progress(len(t_a), total)
    finally:
        reader.close()
    if len(t_j) < 2 or not t_a:
        raise RecordingError(f"the bag holds {len(t_j)} joint states and {len(t_a)} A-scans; both streams are needed")
    return _joint_stream(np.array(t_j), np.array(q_j)), np.array(t_a)


def _joint_stream(t: np.ndarray, q: np.ndarray) -> JointStream:
    """The joint stream sorted by stamp, duplicates dropped; RecordingError on angles that
    are not finite or not radians."""
    if not np.all(np.isfinite(q)):
        raise RecordingError("joint positions hold NaN or infinity")
    if np.abs(q).max() > 2.0 * np.pi:
        raise RecordingError(f"joint positions reach {np.abs(q).max():.1f}: more than 2 pi, so not radians "
                             "(JointState positions are rad; degrees?)")
    order = np.argsort(t, kind="stable")
    t, q = t[order], q[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return JointStream(t[keep], q[keep])


def _read_csv(path: Path, header_start: str) -> tuple[list[str], np.ndarray]:
    with open(path) as f:
        header = f.readline().strip().split(",")
    if not header or header[0] != header_start:
        raise RecordingError(f"{path}: the first column must be {header_start!r}, got {header[0]!r}")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise RecordingError(f"{path}: not numeric CSV ({exc})") from None
    if data.shape[1] != len(header):
        raise RecordingError(f"{path}: {data.shape[1]} columns, the header names {len(header)}")
    return header, data


def read_csv_pair(folder, on_ascan, n_samples: int) -> tuple[JointStream, np.ndarray, np.ndarray | None]:
    """(joint stream, OCT stamps (N,) s, distances (N,) mm or None) of a CSV pair folder
    (module docstring): A-scans go to `on_ascan`; an oct.csv's distances are returned
    instead. RecordingError on missing files, wrong headers or units."""
    folder = Path(folder)
    joints = folder / "joints.csv"
    if not joints.exists():
        raise RecordingError(f"--recording {folder}: a CSV recording needs joints.csv (t_s,q1_rad..q6_rad)")
    header, J = _read_csv(joints, "t_s")
    if header[1:] != [f"q{k}_rad" for k in range(1, 7)]:
        raise RecordingError(f"{joints}: columns must be t_s,q1_rad,...,q6_rad (joint angles in rad), got {','.join(header)}")
    stream = _joint_stream(J[:, 0], J[:, 1:7])
    if (folder / "oct.csv").exists():
        header, D = _read_csv(folder / "oct.csv", "t_s")
        if header != ["t_s", "distance_mm"]:
            raise RecordingError(f"{folder / 'oct.csv'}: columns must be t_s,distance_mm, got {','.join(header)}")
        return stream, D[:, 0], D[:, 1]
    if not (folder / "ascans.csv").exists():
        raise RecordingError(f"--recording {folder}: a CSV recording needs ascans.csv (t_s,a0..a{n_samples - 1}) or oct.csv")
    header, A = _read_csv(folder / "ascans.csv", "t_s")
    if len(header) != n_samples + 1:
        raise RecordingError(f"{folder / 'ascans.csv'}: {len(header) - 1} samples per A-scan, the OCT engine has {n_samples}")
    for row in A[:, 1:]:
        on_ascan(row)
    return stream, A[:, 0], None
