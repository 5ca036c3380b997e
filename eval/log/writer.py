"""The run log: an MCAP file that Foxglove opens and `vitreoguard replay` re-runs, and a
reader that tolerates the truncated tail of a killed run.

Channels (schemas in eval.log.schemas, JSON): "/filter/config" once at the start;
"/robot/joint_states", "/oct/ascan", "/oct/distance", "/model", "/filter/inputs",
"/filter/outputs", "/filter/status", "/clearance" (mm, s, rad; W frame), each message
with its simulation time `t` (s). Foxglove's well-known types (eval.log.scene,
foxglove-sdk, protobuf): "/tf" (foxglove.FrameTransforms), "/scene"
(foxglove.SceneUpdate) in metres, "/log" (foxglove.Log: run events).

Times: a message's log and publish time (and a Foxglove message's timestamp) is the
run's wall-clock start (`RunLogger.start_ns`, ns since the epoch, also in the file's
"time" metadata as start_time_ns) + its simulation time; the simulation time itself is
the message's `t` (the scene's entities carry it as metadata 'sim_time_s').

Crash safety: the writer closes its chunk and flushes the file whenever the simulation
time crosses a whole second and whenever a second of wall time has passed since the last
flush, so a killed run leaves every message up to the last whole second of simulation
(and of wall time) readable by `read_log(..., allow_truncated=True)`.
"""
from __future__ import annotations

import base64
import json
import math
import time
from pathlib import Path

import numpy as np
from foxglove import Channel, Context, Schema, open_mcap
from foxglove.channels import FrameTransformsChannel, LogChannel, PointCloudChannel, SceneUpdateChannel
from foxglove.mcap import MCAPCompression, MCAPWriteOptions

from eval.interrupts import is_interrupt
from eval.log import codec
from eval.log import scene
from eval.log import steps as step_records
from eval.log.reader import MCAP_MAGIC, LogReadError, RunLog, TruncatedLogError, read_log  # noqa: F401  (this module's interface)
from eval.log.scene import M_PER_MM, quaternion_xyzw  # noqa: F401  (part of this module's interface)
from eval.log.robot_scene import point_cloud
from eval.log.schemas import CHANNELS
from models.local.field import FieldValues
from safety import FilterConfig, FilterInputs, FilterOutput

_KIND_INDEX = {"prior": 0, "sphere": 1, "ellipsoid": 2}
_JSON = json.JSONEncoder(allow_nan=False, separators=(",", ":"))  # one encoder: json.dumps with options builds one per call
_FOXGLOVE_CHANNELS = {"/tf": FrameTransformsChannel, "/scene": SceneUpdateChannel, "/log": LogChannel,
                      "/oct/points": PointCloudChannel}



def time_ns(t_s) -> int:
    """Simulation time t_s (s, finite, >= 0) in ns."""
    t = float(t_s)
    if not (math.isfinite(t) and t >= 0.0):
        raise ValueError(f"t_s must be a finite time >= 0 s, got {t_s!r}")
    return int(round(t * 1e9))


def _json_number(x) -> str:
    """x as a JSON number (float repr, as json.dumps writes it), "null" where _opt gives None."""
    v = _opt(x)
    return "null" if v is None else repr(v)


def _opt(x) -> float | None:
    """A finite float, or None (JSON null) for NaN/inf/None: what Foxglove plots skip."""
    return None if x is None or not math.isfinite(float(x)) else float(x)


class RunLogger:
    """Writes one run's MCAP log; use as a context manager (`with RunLogger(path, cfg) as log:`).

    `filter_config` is logged once on "/filter/config" (replay rebuilds the filter from it);
    `flush_every_s` bounds what a killed run can lose, in simulation and in wall time (s);
    `metadata` goes to the file's "run" metadata; `start_ns` is the run's wall-clock start
    (ns since the epoch; default: now), to which the simulation time is added for log times.
    The writer is foxglove-sdk's (zstd chunks, CRCs of chunks and data section).
    """

    def __init__(self, path, filter_config: FilterConfig | None = None, flush_every_s: float = 1.0,
                 metadata: dict | None = None, start_ns: int | None = None):
        if not (math.isfinite(flush_every_s) and flush_every_s > 0):
            raise ValueError(f"flush_every_s must be finite and > 0 s, got {flush_every_s}")
        self.path = Path(path)
        self.flush_every_s = float(flush_every_s)
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
        if self.start_ns < 0:
            raise ValueError(f"start_ns must be >= 0 ns since the epoch, got {start_ns}")
        # this log's channels only (several logs may be open at once); kept: its channels close with it
        self._context = context = Context()
        options = MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_threads=0, profile="",
                                   calculate_chunk_crcs=True, calculate_data_section_crc=True)
        self._writer = open_mcap(self.path, allow_overwrite=True, context=context, writer_options=options)
        self._closed = False
        self._channels = {topic: Channel(topic, schema=Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode()),
                                         message_encoding="json", context=context)
                          for topic, (name, schema) in CHANNELS.items()}
        self._foxglove = {topic: cls(topic, context=context) for topic, cls in _FOXGLOVE_CHANNELS.items()}
        self._step_channel = Channel(step_records.STEP_TOPIC, schema=Schema(
            name=step_records.STEP_TYPE, encoding="protobuf", data=step_records.FILTER_STEP_SCHEMA),
            message_encoding="protobuf", context=context)
        # the channels' own loggers of encoded bytes (foxglove Channel.base): a step's few messages skip the
        # Python wrapper's per-call encoding checks
        self._raw = {topic: ch.base for topic, ch in self._channels.items()}
        self._raw_step = self._step_channel.base
        self._setup_logged = False
        self._last_model, self._n_models = None, 0  # the last (shape, kind) logged on /filter/models, and how many
        self._writer.write_metadata("time", {"start_time_ns": str(self.start_ns),
                                             "log_time": "start_time_ns + simulation time (ns)"})
        if metadata:
            self._writer.write_metadata("run", {str(k): str(v) for k, v in metadata.items()})
        self.steps = 0
        self._last_ns = 0  # simulation time of the newest message
        self._last_flush = (0, time.monotonic())  # (whole flush periods of simulation time, wall time)
        self._write("/filter/config", 0, codec.config_to_json(filter_config or FilterConfig()))
        self._writer.flush()

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and not self._closed:  # say in the log why it ends here
            name = "KeyboardInterrupt" if is_interrupt(exc) else exc_type.__name__
            self.log_event(self._last_ns * 1e-9, f"run ended early: {name}", "error")
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close the file; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._writer.close()

    def _write(self, topic: str, ns: int, msg: dict) -> None:
        if self._closed:
            raise ValueError(f"the run log {self.path} is closed")
        self._last_ns = ns
        self._raw[topic].log(_JSON.encode(msg).encode(), self.start_ns + ns)

    def _write_foxglove(self, topic: str, ns: int, message) -> None:
        if self._closed:
            raise ValueError(f"the run log {self.path} is closed")
        self._last_ns = ns
        self._foxglove[topic].log(message, log_time=self.start_ns + ns)
        self._maybe_flush(ns)

    def _log(self, topic: str, ns: int, msg: dict) -> None:
        self._write(topic, ns, msg)
        self._maybe_flush(ns)

    def _maybe_flush(self, ns: int) -> None:
        """Close the chunk and flush the file when the simulation time enters a new period
        of `flush_every_s` (whatever wall-time flushes came between) or that much wall time
        has passed: called after each whole record group, so a step is never split."""
        period, t_wall = self._last_flush
        now, new_period = time.monotonic(), int(ns * 1e-9 // self.flush_every_s)
        if new_period > period or now - t_wall >= self.flush_every_s:
            self._writer.flush()
            self._last_flush = (max(period, new_period), now)

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
        self.log_distances([t_s], [distance_mm], [valid], [confidence])

    def log_distances(self, T_s, distances_mm, valid, confidence) -> None:
        """One "/oct/distance" message per sample of a packet: times T_s (s), distances (mm),
        valid flags and confidences, as sequences of Python scalars (2 kHz: each message
        formatted directly, the same JSON as the encoder's in a third of its time)."""
        if self._closed:
            raise ValueError(f"the run log {self.path} is closed")
        log, start, ns = self._raw["/oct/distance"].log, self.start_ns, None
        for t, d, ok, c in zip(T_s, distances_mm, valid, confidence):
            ns = time_ns(t)
            log(f'{{"t":{float(t)!r},"distance_mm":{_json_number(d)},"valid":{"true" if ok else "false"},'
                f'"confidence":{_json_number(c)}}}'.encode(), start + ns)
        if ns is not None:
            self._last_ns = ns
            self._maybe_flush(ns)

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

    def log_setup(self, setup: dict) -> None:
        """The closed loop's scenario and monitored points (eval.log.steps.setup_to_json):
        what replay rebuilds the kinematics of the log_step records after it with; logged
        again only when it changes (another trocar)."""
        if setup != self._setup_logged:
            self._write("/filter/setup", self._last_ns, setup)
            self._setup_logged = setup

    def _model_index(self, ns: int, t_s: float, shape, kind: str | None) -> int:
        """The index of (shape, kind) on /filter/models, logging it when it is not the last one."""
        last = self._last_model  # only the last is kept: the local boundary logs a new one every step
        if last is None or last[0] is not shape or last[1] != kind:
            self._last_model, self._n_models = (shape, kind), self._n_models + 1
            shape_json = shape if shape is step_records.STEP_VALUES else codec.shape_to_json(shape)
            self._write("/filter/models", ns, {"t": float(t_s), "index": self._n_models - 1, "kind": kind,
                                               "shape": shape_json})
        return self._n_models - 1

    def log_step(self, t_s, q, command, shape, kind: str | None, model_time_s: float, sensor_time_s: float,
                 margin_mm: float, trusted, misfit_mm, output, pending=None) -> None:
        """One closed-loop filter step as a compact record on /filter/step (eval.log.steps):
        joint angles q (6,) rad, `command` (4,) [v_W mm/s, roll rad/s], the model `shape`
        and `kind` (None: the prior) the filter used, the model's and sensor's times (s),
        `margin_mm`, the boundary points' `trusted` flags and `misfit_mm`, and the filter's
        `output` (safety.FilterOutput), the actuator's `pending` displacements (r, 6) rad
        (None: an ideal actuator). Needs log_setup first (replay needs it)."""
        if not self._setup_logged:
            raise ValueError("log_setup must come before the first log_step: replay rebuilds the kinematics from it")
        ns = time_ns(t_s)
        values = shape if isinstance(shape, FieldValues) else None  # in the step record
        index = self._model_index(ns, t_s, step_records.STEP_VALUES if values is not None else shape, kind)
        if self._closed:
            raise ValueError(f"the run log {self.path} is closed")
        self._last_ns = ns
        self._raw_step.log(step_records.encode_step(self.steps, float(t_s), q, command, index, model_time_s,
                                                    sensor_time_s, margin_mm, trusted, misfit_mm, output,
                                                    pending, values),
                           self.start_ns + ns)
        self.steps += 1
        self._maybe_flush(ns)

    def log_clearance(self, t_s, p_W_tip_port, model, true_eye=None) -> None:
        """"/clearance": the model's (and `true_eye`'s, when given) clearance of the tip and
        the port at p_W_tip_port (2, 3) mm."""
        P = np.asarray(p_W_tip_port, dtype=float)
        out = {}
        for suffix, shape in (("_mm", model), ("_true_mm", true_eye)):
            h = shape.signed_distance(P) if shape is not None and np.isfinite(P).all() else (None, None)
            out.update({"tip" + suffix: _opt(h[0]), "port" + suffix: _opt(h[1])})
        self._log("/clearance", time_ns(t_s), {"t": float(t_s), **out})

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
        self._write_foxglove("/tf", ns, scene.frame_transforms(self.start_ns + ns, X_W))

    def log_scene(self, t_s, eye=None, beam=None, p_W_trocar=None, lens=None, boundary=None, robot=None) -> None:
        """The 3D scene in W: the eye model `eye` (Sphere/Ellipsoid, translucent), the
        `boundary` the filter keeps, the lens keep-out `lens`, the OCT `beam` as
        (p_W_start, p_W_end) mm, the trocar point, and the `robot`'s links
        (eval.log.robot_scene.RobotScene; their frames come with log_frames)."""
        ns = time_ns(t_s)
        extra = () if robot is None else robot.entities(self.start_ns + ns)
        self._write_foxglove("/scene", ns, scene.scene_update(self.start_ns + ns, float(t_s), eye, beam, p_W_trocar, lens,
                                                              boundary, extra))

    def log_points(self, t_s, P_W) -> None:
        """Measured retinal points P_W (N, 3) mm, new since the last call, as a
        foxglove.PointCloud on "/oct/points" (a decay time in Foxglove's 3D panel accumulates them)."""
        ns = time_ns(t_s)
        self._write_foxglove("/oct/points", ns, point_cloud(self.start_ns + ns, P_W))

    def log_event(self, t_s, text: str, level: str = "info") -> None:
        """A run event (`text`, level "debug" | "info" | "warning" | "error") on "/log"."""
        ns = time_ns(t_s)
        self._write_foxglove("/log", ns, scene.log_message(self.start_ns + ns, text, level))
