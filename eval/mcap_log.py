"""The run log: an MCAP file (JSON messages) that Foxglove opens and `vitreoguard replay`
re-runs, and a reader that tolerates the truncated tail of a killed run.

Channels (schemas in eval.mcap_schemas): "/filter/config" once at the start;
"/robot/joint_states", "/oct/ascan", "/oct/distance", "/model", "/filter/inputs",
"/filter/outputs", "/filter/status", "/clearance" (mm, s, rad; W frame); "/tf"
(foxglove.FrameTransforms) and "/scene" (foxglove.SceneUpdate) in metres. Log and
publish times are the simulation time in ns.

Crash safety: the writer closes its chunk and flushes the file whenever a second of
simulation or wall time has passed since the last flush, so a killed run leaves every
message up to the last second readable by `read_log(..., allow_truncated=True)`.
"""
from __future__ import annotations

import base64
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Header, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from eval import mcap_codec as codec
from eval.mcap_schemas import CHANNELS
from safety import FilterConfig, FilterInputs, FilterOutput

M_PER_MM = 1e-3  # Foxglove's 3D panel works in metres
MCAP_MAGIC = b"\x89MCAP0\r\n"  # the first and last 8 bytes of every MCAP file
_KIND_INDEX = {"prior": 0, "sphere": 1, "ellipsoid": 2}
_JSON = json.JSONEncoder(allow_nan=False, separators=(",", ":"))  # one encoder: json.dumps with options builds one per call


class LogReadError(ValueError):
    """The file is not a readable run log; the message says why and where."""


class TruncatedLogError(LogReadError):
    """The file ends before its footer: a killed run's log (readable with allow_truncated)."""


def time_ns(t_s) -> int:
    """Log time in ns of a simulation time t_s (s, finite, >= 0)."""
    t = float(t_s)
    if not (math.isfinite(t) and t >= 0.0):
        raise ValueError(f"t_s must be a finite time >= 0 s, got {t_s!r}")
    return int(round(t * 1e9))


def _opt(x) -> float | None:
    """A finite float, or None (JSON null) for NaN/inf/None: what Foxglove plots skip."""
    return None if x is None or not math.isfinite(float(x)) else float(x)


def quaternion_xyzw(R) -> list[float]:
    """Unit quaternion [x, y, z, w] (w >= 0) of the rotation matrix R (3, 3)."""
    R = np.asarray(R, dtype=float)
    q = np.empty(4)
    tr = np.trace(R)
    if tr > 0.0:  # the branch with the largest component keeps the division well conditioned
        s = 2.0 * math.sqrt(1.0 + tr)
        q[:] = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return (q if q[3] >= 0 else -q).tolist()


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _vec(p_mm) -> dict:
    x, y, z = (float(v) * M_PER_MM for v in p_mm)
    return {"x": x, "y": y, "z": z}


def _pose(p_mm, R=np.eye(3)) -> dict:
    return {"position": _vec(p_mm), "orientation": dict(zip("xyzw", quaternion_xyzw(R)))}


def _entity(ns: int, id_: str, spheres=(), lines=()) -> dict:
    empty = {k: [] for k in ("metadata", "arrows", "cubes", "cylinders", "triangles", "texts", "models")}
    return {"timestamp": _stamp(ns), "frame_id": "W", "id": id_, "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": False, **empty, "spheres": list(spheres), "lines": list(lines)}


def _shape_sphere(shape, color) -> dict:
    """A Foxglove sphere primitive (an ellipsoid when the sizes differ) of a Sphere or Ellipsoid."""
    radii = np.full(3, shape.radius) if hasattr(shape, "radius") else shape.radii
    R = getattr(shape, "rotation", np.eye(3))
    return {"pose": _pose(shape.center, R), "size": _vec(2.0 * radii), "color": color}


class RunLogger:
    """Writes one run's MCAP log; use as a context manager (`with RunLogger(path, cfg) as log:`).

    `filter_config` is logged once on "/filter/config" (replay rebuilds the filter from it);
    `flush_every_s` bounds what a killed run can lose, in simulation and in wall time (s).
    """

    def __init__(self, path, filter_config: FilterConfig | None = None, flush_every_s: float = 1.0,
                 metadata: dict | None = None):
        if not (math.isfinite(flush_every_s) and flush_every_s > 0):
            raise ValueError(f"flush_every_s must be finite and > 0 s, got {flush_every_s}")
        self.path = Path(path)
        self.flush_every_s = float(flush_every_s)
        self._file = open(self.path, "wb")
        # the data-section CRC lets a reader detect any damaged byte of a complete log
        self._writer = Writer(self._file, compression=CompressionType.ZSTD, enable_data_crcs=True)
        self._writer.start(profile="", library="vitreoguard")
        self._channels = {}
        for topic, (name, schema) in CHANNELS.items():
            sid = self._writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic, "json", sid)
        if metadata:
            self._writer.add_metadata("run", {str(k): str(v) for k, v in metadata.items()})
        self.steps = 0
        self._last_flush = (0.0, time.monotonic())
        self._write("/filter/config", 0, codec.config_to_json(filter_config or FilterConfig()))
        self._writer.flush()

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close the file; idempotent."""
        if self._file.closed:
            return
        self._writer.finish()
        self._file.close()

    def _write(self, topic: str, ns: int, msg: dict) -> None:
        if self._file.closed:
            raise ValueError(f"the run log {self.path} is closed")
        data = _JSON.encode(msg).encode()
        self._writer.add_message(self._channels[topic], ns, data, ns)

    def _log(self, topic: str, ns: int, msg: dict) -> None:
        self._write(topic, ns, msg)
        self._maybe_flush(ns)

    def _maybe_flush(self, ns: int) -> None:
        """Close the chunk and flush the file once a second (simulation or wall time) has
        passed: called after each whole record group, so a step is never split."""
        t_sim, t_wall = self._last_flush
        now = time.monotonic()
        if ns * 1e-9 - t_sim >= self.flush_every_s or now - t_wall >= self.flush_every_s:
            self._writer.flush()
            self._last_flush = (ns * 1e-9, now)

    def log_joint_states(self, t_s, q, qdot, names) -> None:
        """Joint angles q (n,) rad and rates qdot (n,) rad/s, with the joint `names`."""
        q, qdot = np.asarray(q, dtype=float), np.asarray(qdot, dtype=float)
        if not (q.ndim == 1 and q.shape == qdot.shape and len(names) == len(q)):
            raise ValueError(f"q, qdot and names must have the same length n, got {q.shape}, {qdot.shape}, {len(names)}")
        self._log("/robot/joint_states", time_ns(t_s), {"t": float(t_s), "names": [str(n) for n in names],
                                                          "q": codec.json_array(q), "qdot": codec.json_array(qdot)})

    def log_ascan(self, t_s, samples, valid: bool, reason: str = "") -> None:
        """One A-scan: `samples` (N,) intensities (stored as float32), whether a distance
        could be extracted (`valid`) and if not, why (`reason`)."""
        s = np.asarray(samples, dtype="<f4").ravel()
        self._log("/oct/ascan", time_ns(t_s), {"t": float(t_s), "n_samples": int(s.size),
                                                 "samples": base64.b64encode(s.tobytes()).decode("ascii"),
                                                 "valid": bool(valid), "reason": str(reason)})

    def log_distance(self, t_s, distance_mm, valid: bool, confidence: float) -> None:
        """The distance (mm) along the beam extracted from an A-scan, and its confidence."""
        self._log("/oct/distance", time_ns(t_s), {"t": float(t_s), "distance_mm": _opt(distance_mm),
                                                    "valid": bool(valid), "confidence": _opt(confidence)})

    def log_model(self, t_s, kind: str, sphere=None, ellipsoid=None, n_points: int = 0, criteria=None) -> None:
        """The eye model (W, mm): `kind` "prior" | "sphere" | "ellipsoid", its current
        `sphere` and `ellipsoid` (either may be None), the points it holds and its
        transition `criteria` {name: (value, met)} (models.adaptive.model.ModelUpdate.criteria)."""
        if kind not in _KIND_INDEX:
            raise ValueError(f"kind must be one of {sorted(_KIND_INDEX)}, got {kind!r}")
        crit = {str(k): {"value": _opt(v[0]), "met": bool(v[1])} for k, v in (criteria or {}).items()}
        self._log("/model", time_ns(t_s), {
            "t": float(t_s), "kind": kind, "kind_index": _KIND_INDEX[kind], "n_points": int(n_points),
            "sphere": codec.shape_to_json(sphere), "ellipsoid": codec.shape_to_json(ellipsoid), "criteria": crit})

    def log_model_update(self, t_s, update) -> None:
        """log_model from a models.adaptive.model.ModelUpdate (one history entry)."""
        self.log_model(t_s, update.kind, update.sphere, update.ellipsoid, update.n_points, update.criteria)

    def log_filter_step(self, inputs: FilterInputs, output: FilterOutput, true_eye=None) -> None:
        """One filter step at inputs.t_s: "/filter/inputs" (all of `inputs`, for replay),
        "/filter/outputs", "/filter/status" and "/clearance" (model clearance of the
        points named "tip" and "port"; also against `true_eye`, when given: any shape
        answering signed_distance of W points)."""
        ns, t = time_ns(inputs.t_s), float(inputs.t_s)
        head = {"t": t, "step": self.steps}
        self._write("/filter/inputs", ns, {**head, **codec.inputs_to_json(inputs)})
        self._write("/filter/outputs", ns, {**head, "qdot": codec.json_array(output.qdot)})
        self._write("/filter/status", ns, {
            **head, "ok": bool(output.ok), "reason": str(output.reason), "active": list(output.active),
            "n_active": len(output.active), "min_clearance_mm": _opt(output.min_clearance_mm),
            "cutter_allowed": bool(output.cutter_allowed), "intervened": bool(output.intervened),
            "solve_us": float(output.solve_us)})
        self._write("/clearance", ns, {"t": t, **self._clearances(inputs, true_eye)})
        self.steps += 1
        self._maybe_flush(ns)

    @staticmethod
    def _clearances(inputs: FilterInputs, true_eye) -> dict:
        pts = {p.name: p.p_W for p in inputs.boundary_points if p.name in ("tip", "port")}
        names = [n for n in ("tip", "port") if n in pts and np.isfinite(pts[n]).all()]
        out = {}
        for suffix, shape in (("_mm", inputs.model), ("_true_mm", true_eye)):
            h = dict(zip(names, shape.signed_distance(np.array([pts[n] for n in names])))) if shape is not None and names else {}
            out.update({n + suffix: _opt(h.get(n)) for n in ("tip", "port")})
        return out

    def log_frames(self, t_s, X_W: dict) -> None:
        """Poses X_WA (4, 4) homogeneous, mm, of frames A ("F", "T", "S", "C", "E", ...) in W, as /tf."""
        ns = time_ns(t_s)
        transforms = []
        for name, X in X_W.items():
            X = np.asarray(X, dtype=float)
            if X.shape != (4, 4) or not np.all(np.isfinite(X)):
                raise ValueError(f"X_W[{name!r}] must be a finite (4, 4) pose, got shape {X.shape}")
            transforms.append({"timestamp": _stamp(ns), "parent_frame_id": "W", "child_frame_id": str(name),
                               "translation": _vec(X[:3, 3]), "rotation": dict(zip("xyzw", quaternion_xyzw(X[:3, :3])))})
        self._write("/tf", ns, {"transforms": transforms})
        self._maybe_flush(ns)

    def log_scene(self, t_s, eye=None, beam=None, p_W_trocar=None, lens=None) -> None:
        """The 3D scene in W: the eye model `eye` (Sphere/Ellipsoid, translucent), the lens
        keep-out `lens`, the OCT `beam` as (p_W_start, p_W_end) mm, the trocar point."""
        ns = time_ns(t_s)
        entities = []
        if eye is not None:
            color = {"r": 1.0, "g": 0.55, "b": 0.1, "a": 0.25} if hasattr(eye, "radius") else {"r": 0.1, "g": 0.8, "b": 0.9, "a": 0.25}
            entities.append(_entity(ns, "eye_model", spheres=[_shape_sphere(eye, color)]))
        if lens is not None:
            entities.append(_entity(ns, "lens", spheres=[_shape_sphere(lens, {"r": 0.3, "g": 0.3, "b": 1.0, "a": 0.3})]))
        if beam is not None:
            line = {"type": 0, "pose": _pose(np.zeros(3)), "thickness": 2.0, "scale_invariant": True,
                    "points": [_vec(beam[0]), _vec(beam[1])], "color": {"r": 1.0, "g": 0.0, "b": 0.0, "a": 1.0},
                    "colors": [], "indices": []}
            entities.append(_entity(ns, "beam", lines=[line]))
        if p_W_trocar is not None:
            trocar = {"pose": _pose(p_W_trocar), "size": _vec(np.full(3, 1.0)), "color": {"r": 1.0, "g": 0.9, "b": 0.0, "a": 1.0}}
            entities.append(_entity(ns, "trocar", spheres=[trocar]))
        self._write("/scene", ns, {"deletions": [], "entities": entities})
        self._maybe_flush(ns)


class _WholeReads:
    """A file whose short reads raise EndOfFile: a file cut inside a record (a killed
    writer) then reads as truncated rather than as garbage."""

    def __init__(self, f):
        self._f = f

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if n is not None and 0 < n != len(data):
            raise EndOfFile()
        return data


@dataclass
class RunLog:
    """A log's decoded messages: `messages[topic]` is a list of (log_time_ns, dict);
    `schemas[topic]` the schema name; `truncated` True when the file ends early."""

    messages: dict = field(default_factory=dict)
    schemas: dict = field(default_factory=dict)
    truncated: bool = False

    def count(self, topic: str) -> int:
        return len(self.messages.get(topic, ()))


def read_log(path, topics=None, allow_truncated: bool = False) -> RunLog:
    """Read the run log at `path` by streaming its records (no summary needed).

    `topics`: decode only these (None: all). A file that ends before its footer (a killed
    run) raises LogReadError unless `allow_truncated`, when everything up to the last
    complete chunk is returned with `truncated` True. Anything else wrong (not an MCAP
    file, a bad CRC, undecodable JSON) raises LogReadError saying what and where.
    """
    path = Path(path)
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise LogReadError(f"cannot open {path}: {exc.strerror or exc}") from None
    log = RunLog()
    channels, schemas, header = {}, {}, False
    with f:
        start = f.read(len(MCAP_MAGIC))
        if start != MCAP_MAGIC:
            what = "empty" if not start else f"it starts with {start!r}, not the MCAP magic"
            raise LogReadError(f"{path}: not an MCAP file ({what})")
        f.seek(0)
        try:
            for rec in StreamReader(_WholeReads(f), validate_crcs=True, record_size_limit=1 << 30).records:
                if isinstance(rec, Header):
                    header = True
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                    log.schemas[rec.topic] = schemas.get(rec.schema_id, "")
                elif isinstance(rec, Message):
                    topic = channels.get(rec.channel_id)
                    if topic is None:
                        raise LogReadError(f"{path}: message on unknown channel {rec.channel_id}")
                    if topics is not None and topic not in topics:
                        continue
                    try:
                        log.messages.setdefault(topic, []).append((rec.log_time, json.loads(rec.data)))
                    except (ValueError, UnicodeDecodeError) as exc:
                        raise LogReadError(f"{path}: undecodable JSON on {topic} at {rec.log_time} ns: {exc}") from None
        except EndOfFile:
            if not header:
                raise LogReadError(f"{path}: truncated before its MCAP header ({path.stat().st_size} bytes)") from None
            if not allow_truncated:
                raise TruncatedLogError(f"{path}: truncated: the file ends before its footer (a killed run?) "
                                        f"after {sum(map(len, log.messages.values()))} readable messages") from None
            log.truncated = True
        except LogReadError:
            raise
        except Exception as exc:  # bad magic, CRC, decompression, record parsing: all mean corrupt
            if not header:
                raise LogReadError(f"{path}: corrupt or truncated MCAP header: {exc}") from None
            raise LogReadError(f"{path}: corrupt MCAP file: {type(exc).__name__}: {exc}") from None
    return log
