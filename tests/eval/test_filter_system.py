"""The loop's filter step (one compiled call: the instrument's kinematics kernel, the eye
model as a distance field, the constraint stack) equals the filter's Python API on the
same step's FilterInputs (the log's record; distances from the shapes' own methods)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eval.experiments.boundary import adversarial_starts
from eval.closed_loop import ClosedLoop, LoopConfig, ModelSnapshot
from planning import SurgeryScenario
from planning.scan import start_posture
from safety import FilterConfig, SafetyFilter
from test_closed_loop import model_from_spiral_beams

QUADRIC = LoopConfig(local_model=False, filter=FilterConfig())  # the quadric model's boundary (margins, trust angle)
QDOT_TOL = 1e-9  # rad/s: the same rows from distances computed two ways (to rounding); only the solver's rounding differs


@pytest.fixture(scope="module")
def setup():
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario)
    loop = ClosedLoop(scenario, QUADRIC)
    starts = adversarial_starts(loop, model.shape, 12, np.random.default_rng(5))
    snaps = {
        "prior": ModelSnapshot("prior", None, 0.0, np.nan, 0, coverage.view()),
        "ellipsoid": ModelSnapshot("ellipsoid", model.shape, 0.0, 0.01, model.n_points, coverage.view(model.shape)),
        "sphere": ModelSnapshot("sphere", model.sphere, 0.0, 0.3, model.n_points, coverage.view(model.sphere)),
        "no coverage": ModelSnapshot("ellipsoid", model.shape, 0.0, 0.01, model.n_points, None),
    }
    return loop, starts, snaps


def api(loop, t, q, command, snap, sensor_t):
    return SafetyFilter(loop.config.filter)(loop.filter.inputs(t, q, command, snap, sensor_t)[0])


def assert_same(out, ref):
    assert out.ok == ref.ok and out.reason == ref.reason
    np.testing.assert_allclose(out.qdot, ref.qdot, rtol=0, atol=QDOT_TOL)
    assert out.active == ref.active and out.cutter_allowed == ref.cutter_allowed and out.intervened == ref.intervened
    assert out.min_clearance_mm == pytest.approx(ref.min_clearance_mm, abs=1e-12, nan_ok=True)


@settings(max_examples=120)
@given(start=st.integers(0, 11), kind=st.sampled_from(["prior", "ellipsoid", "sphere", "no coverage"]),
       dq=st.lists(st.floats(-0.02, 0.02), min_size=6, max_size=6),
       v=st.lists(st.floats(-25.0, 25.0), min_size=3, max_size=3), roll=st.floats(-3.0, 3.0))
def test_the_loop_step_equals_the_api_on_its_inputs(setup, start, kind, dq, v, roll):
    loop, starts, snaps = setup
    q, command = starts[start] + np.array(dq), np.array([*v, roll])
    loop.filter.stack.reset()  # no remembered active set: the API has none either
    out = loop.filter.filter_step(0.001, q, command, snaps[kind], 0.0)[0]
    assert_same(out, api(loop, 0.001, q, command, snaps[kind], 0.0))


def test_faults_are_worded_by_the_step_that_finds_them(setup):
    loop, starts, snaps = setup
    snap, q = snaps["ellipsoid"], starts[0]
    stale = loop.config.filter.max_sensor_age_s + 0.01
    cases = [([np.nan, 0.0, 0.0, 0.0], 0.0, "non-finite v_cmd_W"), ([500.0, 0.0, 0.0, 0.0], 0.0, "absurd command speed"),
             ([1.0, 0.0, 0.0, 0.0], -stale, "stale sensor")]
    for command, sensor_t, reason in cases:
        out = loop.filter.filter_step(0.001, q, np.array(command), snap, sensor_t)[0]
        assert not out.ok and out.reason.startswith(reason) and not out.qdot.any()
        assert api(loop, 0.001, q, np.array(command), snap, sensor_t).reason.startswith(reason)
    out = loop.filter.filter_step(0.001, np.full(6, np.nan), np.zeros(4), snap, 0.0)[0]
    assert not out.ok and out.reason == "non-finite q" and not out.qdot.any()


def test_both_compiled_outcomes_occur(setup):
    loop, starts, snaps = setup
    step, snap, q = loop.filter.filter_step, snaps["ellipsoid"], starts[0]
    slow = step(0.001, q, np.array([0.1, 0.0, 0.0, 0.0]), snap, 0.0)[0]  # the equality optimum holds
    fast = step(0.001, q, np.array([0.0, 0.0, 60.0, 0.0]), snap, 0.0)[0]  # the tip speed polytope binds
    assert slow.ok and not slow.active and fast.ok and "tip_speed" in fast.active


def test_trust_angle_180_trusts_everything(setup):
    loop, starts, snaps = setup
    wide = ClosedLoop(loop.scenario, LoopConfig(trust_angle_deg=180.0, local_model=False, filter=FilterConfig()))
    command = np.array([1.0, 0.0, 0.0, 0.0])
    out = wide.filter.filter_step(0.001, starts[0], command, snaps["ellipsoid"], 0.0)[0]
    assert_same(out, SafetyFilter(wide.config.filter)(wide.filter.inputs(0.001, starts[0], command, snaps["ellipsoid"],
                                                                         0.0)[0]))


def test_the_rcm_follows_the_active_trocar_without_a_new_filter(setup):
    """set_trocar changes the RCM constraint's numbers and the monitored points' trocar:
    the same compiled step, the error and the rows those of the new trocar."""
    loop, starts, snaps = setup
    q, module = starts[0], loop.filter.stack.module
    p_old = loop.filter.p_WC.copy()
    p_new = p_old + np.array([0.0, 3.0, -1.0])
    try:
        loop.filter.set_trocar(p_new)
        _, _, _, _, err = loop.filter.filter_step(0.001, q, np.zeros(4), snaps["ellipsoid"], 0.0)
        assert err == pytest.approx(loop.robot.rcm_error_mm(q, p_new), abs=1e-9)
        x = loop.filter.inputs(0.001, q, np.zeros(4), snaps["ellipsoid"], 0.0)[0]
        A, b = loop.robot.rcm_rows(q, p_new)  # the loop's gain is the default, RCM_GAIN_PER_S
        assert np.allclose(np.abs(x.rcm_A), np.abs(A), atol=1e-9) and np.allclose(np.abs(x.rcm_b), np.abs(b), atol=1e-9)
        assert loop.filter.stack.module is module
    finally:
        loop.filter.set_trocar(p_old)
    with pytest.raises(ValueError, match="p_WC must be 3 finite mm"):
        loop.filter.set_trocar([0.0, np.nan, 0.0])


@pytest.fixture(scope="module")
def local_setup():
    scenario = SurgeryScenario(eye_name="detached")
    model, coverage = model_from_spiral_beams(scenario, local=True)
    loop = ClosedLoop(scenario, LoopConfig(local_model=True))
    snap = loop.model.snapshot_for(model, coverage, 0.0)
    assert snap.field is not None
    starts = adversarial_starts(loop, model.shape, 8, np.random.default_rng(3))
    return loop, starts, {"prior": ModelSnapshot("prior", None, 0.0, np.nan, 0, coverage.view()), "local": snap}


@settings(max_examples=40)
@given(start=st.integers(0, 7), kind=st.sampled_from(["prior", "local"]),
       dq=st.lists(st.floats(-0.02, 0.02), min_size=6, max_size=6),
       v=st.lists(st.floats(-25.0, 25.0), min_size=3, max_size=3))
def test_the_local_model_step_equals_the_api_on_its_inputs(local_setup, start, kind, dq, v):
    loop, starts, snaps = local_setup
    q, command = starts[start] + np.array(dq), np.array([*v, 0.0])
    loop.filter.stack.reset()
    out = loop.filter.filter_step(0.001, q, command, snaps[kind], 0.0)[0]
    assert_same(out, api(loop, 0.001, q, command, snaps[kind], 0.0))


def test_the_local_barrier_shares_the_snapshots_params(local_setup):
    """The loop's model system writes the filter's bound into its field, so the filter's
    barrier (slot "eye") and the model alone (slot "eye_shaft") read the snapshot's own
    params: no ~1 MB copy in the filter's step when the model refreshes its field."""
    loop, _, snaps = local_setup
    eye, shaft, _ = loop.filter.fields(snaps["local"])
    assert eye is shaft is snaps["local"].field.params


def test_the_local_models_shaft_keeps_to_the_larger_of_its_bounds():
    """With the local model the watched shaft points keep to the barrier's bound, as the tip
    does: the larger of the model's h - k sigma and the prior sphere's (inside every
    retina), each a bound on the true clearance. A model of the dense spiral's first rings
    (pitch 0.5 mm, 3 revolutions: a sphere under the local part) knows nothing of the wall
    the shaft points near the trocar face (sigma 2 mm) and, near its centre, its first-order
    distance falls far below the true one: on the model alone the tip at the eye's centre
    has shaft points inside their margin, which no velocity through the trocar moves out
    (the recovery the loop then holds for good); on the larger bound none."""
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario, local=True, pitch_mm=0.5, revolutions=3.0)
    loop = ClosedLoop(scenario, LoopConfig(local_model=True))
    snap = loop.model.snapshot_for(model, coverage, 0.0)
    k, prior, cfg = loop.config.filter.sigma_factor, loop.filter.prior, loop.config.filter
    margin = cfg.d_safe_mm + cfg.calibration_margin_mm
    alone_inside = 0
    for depth_mm in (0.0, 1.0, 2.0):  # the tip at and behind the eye's centre, along E's -z
        q = start_posture(loop.robot, scenario.eye_pose.to_W(np.array([[0.0, 0.0, -depth_mm]]))[0], loop.robot.p_WC)
        x, _ = loop.filter.inputs(0.001, q, np.zeros(4), snap, 0.0)
        shaft = [bp for bp in x.boundary_points if bp.name.startswith("shaft")]
        assert len(shaft) >= 3
        for bp in shaft:
            p = bp.p_W[None]
            bound = float(x.model.signed_distance(p)[0]) - k * bp.margin_mm
            alone = float(snap.field.signed_distance(p)[0]) - k * float(snap.field.uncertainty(p)[0])
            prior_bound = prior.radius - float(np.linalg.norm(bp.p_W - prior.center))
            assert bound == pytest.approx(max(alone, prior_bound), abs=1e-9)
            assert bound <= float(scenario.eye.signed_distance(p)[0])  # a bound on the true clearance
            assert bound > margin
            alone_inside += alone < margin
    assert alone_inside >= 2


@pytest.fixture(scope="module")
def actuated_setup(setup):
    """The loop told a delayed, lagging, acceleration-limited actuator (the fault classes' values)."""
    from safety.actuator import ActuatorModel

    _, starts, snaps = setup
    actuator = ActuatorModel(delay_s=0.005, lag_s=0.02, accel_limit_rad_s2=float(np.radians(1000.0)))
    loop = ClosedLoop(SurgeryScenario(), LoopConfig(local_model=False, filter=FilterConfig(), actuator=actuator))
    return loop, starts, snaps


def actuated_api(loop, q, command, snap, pending):
    x = loop.filter.inputs(0.001, q, command, snap, 0.0, pending)[0]
    return SafetyFilter(loop.config.filter)(x)


@settings(max_examples=80)
@given(start=st.integers(0, 11), kind=st.sampled_from(["prior", "ellipsoid"]),
       pending=st.lists(st.floats(-0.01, 0.01), min_size=42, max_size=42),
       v=st.lists(st.floats(-25.0, 25.0), min_size=3, max_size=3))
def test_the_actuated_loop_step_equals_the_api_on_its_inputs(actuated_setup, start, kind, pending, v):
    """With the actuator's pending displacements in the inputs, the API builds the same
    actuator-aware barriers and RCM rows (and the same planned stops) as the loop: a log
    of a run on a real robot replays."""
    loop, starts, snaps = actuated_setup
    q, command, P = starts[start], np.array([*v, 0.0]), np.array(pending).reshape(7, 6)
    loop.filter.stack.reset()
    out = loop.filter.filter_step(0.001, q, command, snaps[kind], 0.0, P)[0]
    assert_same(out, actuated_api(loop, q, command, snaps[kind], P))


def test_the_api_makes_both_planned_stops_of_the_actuated_loop(actuated_setup):
    """A pending motion that swings the shaft about the trocar by millimetres: "cannot hold
    the trocar"; one that carries the tip into the retina: "cannot brake before the
    boundary". Both from the API on the loop's inputs, as in the loop."""
    loop, starts, snaps = actuated_setup
    snap, q = snaps["ellipsoid"], starts[0]
    x = loop.filter.inputs(0.001, q, np.zeros(4), snap, 0.0)[0]
    tip = x.boundary_points[0]
    g = snap.shape.gradient(tip.p_W[None])[0]  # > 0 inside: the wall lies along -g
    h = snap.shape.signed_distance(tip.p_W[None])[0]
    reasons = set()
    # still to come: the shaft 0.3 mm sideways at the trocar (the tip away from the wall),
    # then the tip past the wall; joint displacements by least squares on the tip's and RCM's rows
    for tip_move, lateral in ((0.3 * g, 0.3), (-(h + 0.5) * g, 0.0)):
        dq = np.linalg.lstsq(np.vstack([tip.J_W, x.rcm_A]), np.concatenate([tip_move, [lateral, 0.0]]), rcond=None)[0]
        P = np.zeros((7, 6))
        P[0] = dq
        loop.filter.stack.reset()
        out = loop.filter.filter_step(0.001, q, np.zeros(4), snap, 0.0, P)[0]
        assert_same(out, actuated_api(loop, q, np.zeros(4), snap, P))
        reasons.add(out.reason)
    assert reasons == {"actuator cannot hold the trocar", "actuator cannot brake before the boundary"}
