"""The paced tip path in the closed loop: its clock waits for a tip that cannot keep up, and
the model-building spiral runs on it when the loop declares a non-ideal actuator."""
from __future__ import annotations

import numpy as np
import pytest
from test_closed_loop import State, deep_start, model_from_spiral_beams

from eval.closed_loop import ClosedLoop, LoopConfig
from eval.experiments.boundary import build_model_by_spiral, spiral_path_W
from eval.experiments.command_sources import PacedTipPath, TipPathCommand
from planning import SurgeryScenario
from safety.actuator import ActuatorModel


@pytest.fixture(scope="module")
def emmetropic():
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario, local=True)
    return ClosedLoop(scenario), State(model, coverage)


def _off_polyline_mm(X: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(N,) mm: each point of X from the polyline P (M, 3)."""
    d = np.full(len(X), np.inf)
    for a, b in zip(P[:-1], P[1:]):
        s = np.clip((X - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(X - (a + s[:, None] * (b - a)), axis=1))
    return d


def test_a_paced_path_waits_for_a_tip_that_cannot_keep_up(emmetropic):
    """A corner (5 mm along x, then 5 mm along -y) at 60 mm/s, three times the filter's tip
    speed limit (20 mm/s), far from the retina. The timed path runs ahead and its feedback
    pulls the tip across the corner; the paced path's clock slows to what the tip can do
    (at the floor the reference moves at 15 mm/s, so the tip stays within hold_mm of it)
    and the tip, heading for a reference at most hold_mm down the path, stays within
    hold_mm / sqrt(2) of the corner's path. The run ends when the paced path is finished:
    the tip within free_mm of its end."""
    loop, model = emmetropic
    q0 = deep_start(loop)
    p0 = loop.robot.pose("T", q0)[1]
    P = np.vstack([p0, p0 + [5.0, 0.0, 0.0], p0 + [5.0, -5.0, 0.0]])
    t = np.array([0.0, 5.0, 10.0]) / 60.0
    timed = loop.run(TipPathCommand(t, P), q0, 1.0, **model.kw())
    paced_path = PacedTipPath(t, P)
    paced = loop.run(paced_path, q0, 1.0, **model.kw())
    tips = lambda run: np.array([loop.robot.pose("T", q)[1] for q in run.q])  # noqa: E731
    off_timed, off_paced = _off_polyline_mm(tips(timed), P), _off_polyline_mm(tips(paced), P)
    assert timed.ok.all() and paced.ok.all()
    assert off_paced.max() <= paced_path.hold_mm / np.sqrt(2.0) < off_timed.max()
    # the tip moved at least the path less free_mm at 20 mm/s
    assert paced_path.finished and (10.0 - paced_path.free_mm) / 20.0 <= paced.t[-1] < 0.99 < timed.t[-1]
    assert np.linalg.norm(tips(paced)[-1] - P[-1]) <= paced_path.free_mm + 0.02  # + one step at 20 mm/s


@pytest.mark.parametrize("lag_s", [0.0, 0.020])
def test_the_model_building_spiral_is_paced_on_a_declared_actuator_lag(lag_s):
    """A short spiral (2 turns, pitch 1.5 mm, 15 mm/s: 1.3 s at full pace) through the loop:
    with the ideal actuator it is the timed path and the run lasts the path's duration (+
    0.05 s); with a declared 20 ms lag it is paced, and the run ends when the path is
    finished: later than the path's duration (the lagged tip trails the reference by more
    than free_mm where the spiral turns and where the boundary holds it), and no later than
    the clock at its floor plus the settling time (0.4 s). Either way the model is given
    the A-scans' beams."""
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario, LoopConfig(local_model=True, actuator=ActuatorModel(lag_s=lag_s)))
    build = build_model_by_spiral(loop, pitch_mm=1.5, revolutions=2.0, truth_grid=20)
    P = spiral_path_W(scenario, 1.5, 2.0)
    duration_s = np.linalg.norm(np.diff(P, axis=0), axis=1).sum() / 15.0
    run = build.run
    end_t = run.t[-1] + 1e-3  # the last control step's period
    if lag_s == 0.0:
        assert end_t == pytest.approx(duration_s + 0.05, abs=2e-3)
    else:
        assert duration_s + 0.05 < end_t <= duration_s / 0.25 + 0.4 + 2e-3
    assert build.model.n_points > 0 and run.ok.mean() > 0.5
    # the loop gives the model each A-scan's beam: unit directions along the shaft, through the trocar (the
    # filter holds the RCM to micrometres over the ~20 mm from the trocar to the retina: well within 0.01 deg)
    # (the paced run ends with its tip settling on the spiral's end: the dwell rule may take nothing from the last packet)
    A, B = build.model.last_accepted, build.model.last_beams
    assert B is not None and B.shape == A.shape and (len(A) > 0 or lag_s > 0.0) and build.model.local.n_samples > 0
    np.testing.assert_allclose(np.linalg.norm(B, axis=1), 1.0, atol=1e-9)
    U = (A - scenario.p_WC) / np.linalg.norm(A - scenario.p_WC, axis=1, keepdims=True)
    assert np.all(np.degrees(np.arccos(np.clip(np.sum(U * B, axis=1), -1.0, 1.0))) < 0.01)


def test_a_slower_scan_of_the_same_spiral_counts_the_same_samples():
    """The same short spiral (2 turns, pitch 1.5 mm) at 15 and at 5 mm/s through the loop:
    the slower scan takes three times the A-scans (2 kHz), and the local model counts the
    same samples from them, its scan lines' length on the retina over sample_length_mm
    (the shares are measured across the beams the loop passes on, so the distance noise of
    the extra A-scans adds no length). Within 2 %: the paths differ only by how closely the
    tip follows the spiral's turns at each speed."""
    counts, points = [], []
    for speed in (15.0, 5.0):
        loop = ClosedLoop(SurgeryScenario(eye_name="staphyloma"), LoopConfig(local_model=True))
        build = build_model_by_spiral(loop, pitch_mm=1.5, revolutions=2.0, truth_grid=20, speed_mm_s=speed)
        counts.append(build.model.local.n_samples)
        points.append(build.model.n_points)
    assert points[1] / points[0] == pytest.approx(3.0, rel=0.05)
    assert counts[1] / counts[0] == pytest.approx(1.0, abs=0.02)
