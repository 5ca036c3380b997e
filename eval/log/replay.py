"""The regression harness: re-run the safety filter on a run log's inputs and compare.

Each logged step is rebuilt into FilterInputs and filtered again with the logged
configuration ("/filter/config"); a step matches when the joint rates agree within
`tol` (rad/s, max abs difference) and ok, reason and the cutter interlock are equal.
A closed loop's log holds compact "/filter/step" records (eval.log.steps), whose
kinematics are rebuilt on the robot of its "/filter/setup"; a log written through
RunLogger.log_filter_step holds every input ("/filter/inputs", "/filter/outputs",
"/filter/status", paired by their `step` number). Both replay, with the actuator the
run was told about: its pending displacements are in every step's inputs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from eval.log import codec, steps
from eval.log.writer import LogReadError, read_log
from safety import SafetyFilter

TOPICS = ("/filter/config", "/filter/inputs", "/filter/outputs", "/filter/status")
COMPACT_TOPICS = (steps.STEP_TOPIC, steps.MODELS_TOPIC, steps.SETUP_TOPIC)
MAX_REPORTED_MISMATCHES = 20


@dataclass
class ReplayResult:
    """`steps` replayed, `mismatches` among them, `max_abs_diff` (rad/s) of qdot over the
    steps whose rates could be compared, `truncated` (a killed run's log, replayed up to its
    last complete step), `examples` the first few mismatches."""

    steps: int
    mismatches: int
    max_abs_diff: float
    truncated: bool
    examples: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.mismatches == 0

    def as_json(self) -> dict:
        return {"steps": self.steps, "mismatches": self.mismatches, "max_abs_diff": self.max_abs_diff,
                "ok": self.ok, "truncated": self.truncated, "examples": self.examples}


def _by_step(messages, topic: str) -> dict:
    out = {}
    for log_time, m in messages:
        step = m.get("step") if isinstance(m, dict) else None
        if isinstance(step, bool) or not isinstance(step, int):
            raise LogReadError(f"{topic}: message at {log_time} ns has no integer 'step'")
        if step in out:
            raise LogReadError(f"{topic}: step {step} appears twice")
        out[step] = m
    return out


def _logged_steps(log) -> list[tuple[int, dict, dict, dict]]:
    """(step, inputs, outputs, status) for every complete step; LogReadError when a complete
    log misses part of a step (a truncated log may lose its last step's tail)."""
    inputs, outputs, status = (_by_step(log.messages.get(t, ()), t) for t in TOPICS[1:])
    if not inputs:
        raise LogReadError("the log holds no filter steps (neither /filter/step nor /filter/inputs messages): nothing to replay")
    steps = []
    for s in sorted(inputs):
        if s in outputs and s in status:
            steps.append((s, inputs[s], outputs[s], status[s]))
        elif not (log.truncated and s == max(inputs)):
            raise LogReadError(f"step {s} has /filter/inputs but lacks its /filter/outputs or /filter/status")
    return steps


def _compare(step: int, logged_out: dict, logged_status: dict, out) -> tuple[float, list[str]]:
    """(max |qdot difference| or NaN if incomparable, what differs)."""
    diffs = []
    try:
        q_logged = codec.array_from_json(logged_out.get("qdot"), f"step {step} qdot")
    except ValueError as exc:
        raise LogReadError(str(exc)) from None
    if q_logged.shape != out.qdot.shape:
        diffs.append(f"qdot shape {q_logged.shape} != replayed {out.qdot.shape}")
        d = math.nan
    else:
        d = float(np.max(np.abs(q_logged - out.qdot))) if out.qdot.size else 0.0
    for key, replayed in (("ok", out.ok), ("reason", out.reason), ("cutter_allowed", out.cutter_allowed)):
        if logged_status.get(key) != replayed:
            diffs.append(f"{key}: logged {logged_status.get(key)!r}, replayed {replayed!r}")
    return d, diffs


def replay(path, tol: float = 1e-9, allow_truncated: bool = False) -> ReplayResult:
    """Replay the run log at `path`; LogReadError when it cannot be read or is incomplete
    (a truncated log only with `allow_truncated`). `tol`: rad/s, finite, >= 0."""
    if not (math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be finite and >= 0 rad/s, got {tol}")
    log = read_log(path, topics=TOPICS + COMPACT_TOPICS, allow_truncated=allow_truncated)
    configs = log.messages.get("/filter/config", [])
    if len(configs) != 1:
        raise LogReadError(f"{path}: expected one /filter/config message, found {len(configs)}")
    try:
        filt = SafetyFilter(codec.config_from_json(configs[0][1]))
    except ValueError as exc:
        raise LogReadError(f"{path}: /filter/config: {exc}") from None
    logged = _compact_steps(log, path, filt.config) if log.count(steps.STEP_TOPIC) else _json_steps(log, path)
    max_diff, mismatches, examples = 0.0, 0, []
    for s, x, logged_out, logged_status in logged:
        d, diffs = _compare(s, logged_out, logged_status, filt(x))
        if math.isfinite(d):
            max_diff = max(max_diff, d)
        if not d <= tol:
            diffs.append(f"qdot differs by {d:.3g} rad/s > tol {tol:g}")
        if diffs:
            mismatches += 1
            if len(examples) < MAX_REPORTED_MISMATCHES:
                examples.append({"step": s, "t": x.t_s, "differences": diffs})
    return ReplayResult(len(logged), mismatches, max_diff, log.truncated, examples)


def _json_steps(log, path) -> list:
    """(step, FilterInputs, outputs, status) of the /filter/inputs records, all decoded before any runs."""
    out = []
    for s, logged_in, logged_out, logged_status in _logged_steps(log):
        try:
            out.append((s, codec.inputs_from_json(logged_in), logged_out, logged_status))
        except ValueError as exc:
            raise LogReadError(f"{path}: /filter/inputs step {s}: {exc}") from None
    return out


def _compact_steps(log, path, config) -> list:
    """(step, FilterInputs, outputs, status) of the /filter/step records: the kinematics
    rebuilt on the robot of /filter/setup for the filter configured by `config`
    (eval.systems.inputs.StepInputs, the loop's own)."""
    from eval.systems.inputs import StepInputs
    from planning.robot import Robot

    setups = log.messages.get(steps.SETUP_TOPIC, [])
    if not setups:
        raise LogReadError(f"{path}: /filter/step records need a /filter/setup message, found none")
    try:
        # one robot per setup (a run through several trocars logs a setup per trocar)
        builds = [(ns, StepInputs(Robot(scenario), points, config))
                  for ns, (scenario, points) in ((ns, steps.setup_from_json(d)) for ns, d in setups)]
        models = {m["index"]: (steps.model_from_json(m["shape"]), m["kind"])
                  for _, m in log.messages.get(steps.MODELS_TOPIC, [])}
    except (ValueError, KeyError, TypeError) as exc:
        raise LogReadError(f"{path}: {exc}") from None
    out = []
    for ns_step, data in log.messages[steps.STEP_TOPIC]:
        # the newest setup logged before the step (a setup is logged after the last step of the trocar before)
        build = next((b for ns, b in reversed(builds) if ns < ns_step), builds[0][1])
        try:
            m = steps.decode_step(data)
            if m.model_index not in models:
                raise ValueError(f"model {m.model_index} is not on /filter/models")
            shape, kind = models[m.model_index]
            q = np.array(m.q)
            ip = build.points_at(q)
            if shape is steps.STEP_VALUES:
                shape = steps.values_of(m, ip.P_W[:build.boundary_count(kind, len(ip.names))])
            x = build(m.t, q, np.array([*m.v_cmd_W, m.roll_rate_cmd]), shape, kind, m.model_time_s,
                      m.sensor_time_s, m.margin_mm, np.array(m.trusted, dtype=bool), np.array(m.misfit_mm), ip,
                      pending=steps.pending_of(m))
        except ValueError as exc:
            raise LogReadError(f"{path}: /filter/step {len(out)}: {exc}") from None
        out.append((m.step, x, {"qdot": list(m.qdot)},
                    {"ok": m.ok, "reason": m.reason, "cutter_allowed": m.cutter_allowed}))
    return out
