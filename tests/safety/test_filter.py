"""The safety filter on a toy robot whose joints are the tip's Cartesian coordinates
(J = I, mm/rad), inside a spherical retina of radius 12 mm: every number below follows
from that geometry."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Sphere
from safety import FilterConfig, FilterInputs, PointKinematics, SafetyFilter
from safety.stack import RowNames

EYE = Sphere(np.zeros(3), 12.0)
DT = 1e-3
NO_CALIBRATION = FilterConfig(calibration_bound_mm=0.0, calibration_bound_deg=0.0)  # the margin is d_safe alone


def inputs(p, v_cmd, t=0.0, model=EYE, model_time=0.0, sensor_time=0.0, q_min=None, **kw):
    p = np.asarray(p, float)
    return FilterInputs(
        t_s=t, q=p, q_min=np.full(3, -50.0) if q_min is None else q_min, q_max=np.full(3, 50.0),
        qdot_max=np.full(3, 100.0),
        v_cmd_W=np.asarray(v_cmd, float), J_tip=np.eye(3),
        boundary_points=[PointKinematics("tip", p, np.eye(3))],
        model=model, model_time_s=model_time, sensor_time_s=sensor_time, **kw,
    )


def test_free_space_command_passes_unchanged():
    out = SafetyFilter(NO_CALIBRATION)(inputs([0, 0, 0], [3.0, -2.0, 1.0]))
    assert out.ok and not out.intervened
    np.testing.assert_allclose(out.qdot, [3.0, -2.0, 1.0], rtol=0.01)


def test_push_into_the_retina_stops_at_the_margin():
    f = SafetyFilter(NO_CALIBRATION)
    p = np.array([0.0, 0.0, -10.0])  # 2 mm clearance
    clearances = []
    for k in range(3000):  # 3 s of pushing straight down at 5 mm/s
        out = f(inputs(p, [0.0, 0.0, -5.0], t=k * DT, model_time=k * DT, sensor_time=k * DT))
        assert out.ok
        p = p + DT * out.qdot
        clearances.append(float(EYE.signed_distance(p)[0]))
    assert min(clearances) >= 0.5 - 1e-6
    assert clearances[-1] == pytest.approx(0.5, abs=0.01)  # it does get there


def test_the_declared_calibration_bound_adds_to_the_margin():
    cfg = FilterConfig(calibration_bound_mm=0.1, calibration_bound_deg=0.5, calibration_lever_mm=20.0)
    margin = 0.1 + 20.0 * np.tan(np.radians(0.5))  # a point 20 mm along a beam 0.5 deg off lies this far off
    assert cfg.calibration_margin_mm == pytest.approx(margin, rel=1e-12)
    f = SafetyFilter(cfg)
    p = np.array([0.0, 0.0, -10.0])
    for k in range(3000):
        p = p + DT * f(inputs(p, [0.0, 0.0, -5.0], t=k * DT, model_time=k * DT, sensor_time=k * DT)).qdot
    assert float(EYE.signed_distance(p)[0]) == pytest.approx(0.5 + margin, abs=0.01)


def test_tangential_motion_near_the_boundary_is_kept():
    p = np.array([0.0, 0.0, -11.45])  # clearance 0.55 mm: the barrier allows 20/s x 0.05 mm = 1 mm/s inward
    out = SafetyFilter(NO_CALIBRATION)(inputs(p, [2.0, 0.0, -2.0]))
    assert out.ok and out.intervened and "boundary:tip" in out.active
    assert out.qdot[0] == pytest.approx(2.0, rel=0.01)  # the sideways part survives
    assert out.qdot[2] == pytest.approx(-1.0, rel=0.01)  # the inward part is cut to the barrier rate


@settings(max_examples=60)
@given(
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    st.lists(st.floats(-15, 15), min_size=3, max_size=3),
    st.floats(0.5, 11.0),
)
def test_one_step_never_crosses_the_margin(direction, v_cmd, clearance):
    u = np.asarray(direction) + [0, 0, 1e-3]
    u /= np.linalg.norm(u)
    p = u * (12.0 - clearance)
    out = SafetyFilter(NO_CALIBRATION)(inputs(p, v_cmd))
    assert out.ok
    after = float(EYE.signed_distance(p + DT * out.qdot)[0])
    # first order exact; the sphere's curvature costs at most (dt v)^2 / (2 R)
    assert after >= min(clearance, 0.5) - (DT * 20.0) ** 2 / 24.0 - 1e-9


@pytest.mark.parametrize(
    "kw, reason",
    [
        (dict(v_cmd=[np.nan, 0, 0]), "non-finite v_cmd_W"),
        (dict(v_cmd=[500.0, 0, 0]), "absurd command speed"),
        (dict(t=1.0, model_time=0.0, sensor_time=1.0), "stale model"),
        (dict(t=1.0, model_time=1.0, sensor_time=0.5), "stale sensor"),
        (dict(model=None), "no eye model"),
        (dict(roll_rate_cmd=np.nan), "non-finite roll_rate_cmd"),  # no J_roll: the roll is not otherwise read
        (dict(t=0.0, model_time=np.inf), "non-finite time stamp"), (dict(sensor_time=np.inf), "non-finite time stamp"),
        (dict(t=-np.inf), "non-finite time stamp"),
        (dict(q_min=np.array([np.nan, -50.0, -50.0])), "q_min and q_max must not be NaN"),
        (dict(qdot_max=np.array([100.0, 100.0, np.nan])), "qdot_max must be (n,) finite rad/s > 0"),
        (dict(qdot_max=np.array([100.0, 100.0, -1.0])), "qdot_max must be (n,) finite rad/s > 0"),
        (dict(rcm_A=np.array([[np.nan, 0, 0]]), rcm_b=np.array([0.0])), "invalid inputs: LinearEquality"),
        (dict(qdot_max=np.array([100.0, 100.0])), "qdot_max has shape (2,), expected (3,)"),
        (dict(J_roll=np.zeros((1, 2))), "J_roll has shape (1, 2), expected (r, 3)"),
        (dict(pending=np.zeros((1, 2))), "pending has shape (1, 2), expected (r, 3)"),
        (dict(pending=np.array([[0.0, np.nan, 0.0]])), "non-finite pending actuator motion"),
        (dict(boundary_points=[PointKinematics("tip", np.zeros(2), np.eye(3))]), "point tip: p_W (2,) and J_W (3, 3)"),
        (dict(boundary_points=[PointKinematics("tip", np.zeros(3), np.zeros((3, 2)))]), "expected (3,) and (3, 3)"),
        (dict(boundary_points=["tip"]), "a monitored point is a str, not a PointKinematics"),
        # the RCM asks x at 1 mm/s (eased: 0.5, 0) while x lies 1 below its limit (its bound: >= 10 rad/s)
        (dict(rcm_A=np.array([[1.0, 0, 0]]), rcm_b=np.array([1.0]), q_min=np.array([1.0, -50.0, -50.0])), "QP"),
    ],
)
def test_faults_command_zero_velocity_and_say_why(kw, reason):
    args = dict(p=[0, 0, -5.0], v_cmd=[1.0, 0, 0])
    args.update(kw)
    replaced = {k: args.pop(k) for k in ("qdot_max", "boundary_points") if k in args}
    x = inputs(**args)
    if replaced:
        x = FilterInputs(**{**x.__dict__, **replaced})
    out = SafetyFilter(NO_CALIBRATION)(x)
    assert not out.ok and reason in out.reason
    np.testing.assert_array_equal(out.qdot, np.zeros(3))


@pytest.mark.parametrize("h_fallback", [np.nan])
def test_a_nan_fallback_distance_is_a_fault_not_ignored(h_fallback):
    """An untrusted point keeps the tighter of the model and the fallback; a fallback that
    answers NaN is no answer: the step stops (not the model's distance alone). (+inf is a
    field's "no bound", as ModelField.none() answers: the model's distance stands.)"""

    class Broken:
        def signed_distance(self, P):
            return np.full(len(P), h_fallback)

        def gradient(self, P):
            return np.tile([0.0, 0.0, 1.0], (len(P), 1))

    p = np.array([0.0, 0.0, -5.0])
    x = inputs(p, [0.0, 0.0, -1.0], fallback=Broken())
    x = FilterInputs(**{**x.__dict__, "boundary_points": [PointKinematics("tip", p, np.eye(3), trusted=False)]})
    out = SafetyFilter(NO_CALIBRATION)(x)
    assert not out.ok
    np.testing.assert_array_equal(out.qdot, np.zeros(3))


def test_cutter_interlock_follows_the_port_clearance():
    cfg = FilterConfig(calibration_bound_mm=0.0, calibration_bound_deg=0.0, cutter_clearance_mm=1.0)
    for clearance, allowed in ((2.0, True), (0.8, False)):
        p = np.array([0.0, 0.0, -(12.0 - clearance)])
        x = inputs(p, [0.0, 0.0, 0.0])
        x = FilterInputs(**{**x.__dict__, "boundary_points": [PointKinematics("port", p, np.eye(3))]})
        assert SafetyFilter(cfg)(x).cutter_allowed is allowed


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="d_safe_mm"):
        FilterConfig(calibration_bound_mm=0.0, calibration_bound_deg=0.0, d_safe_mm=-0.5)


@pytest.mark.parametrize("solver", ["clarabel", "daqp"])
def test_backends_agree_near_the_boundary(solver):
    p = np.array([0.0, 0.0, -11.45])
    out = SafetyFilter(dataclasses.replace(NO_CALIBRATION, solver=solver))(inputs(p, [2.0, 0.0, -2.0]))
    assert out.ok
    np.testing.assert_allclose(out.qdot, [2.0, 0.0, -1.0], atol=0.02)


def test_an_untrusted_point_keeps_the_fallback_clearance_too():
    """The model allows 2 mm more; the point is marked untrusted: the fallback (a sphere of
    10 mm) decides, so the push stops 0.5 mm inside the fallback, not the model."""
    fallback = Sphere(np.zeros(3), 10.0)
    f = SafetyFilter(NO_CALIBRATION)
    p = np.array([0.0, 0.0, -8.0])
    for k in range(2000):
        x = inputs(p, [0.0, 0.0, -5.0], t=k * DT, model_time=k * DT, sensor_time=k * DT, fallback=fallback)
        x = FilterInputs(**{**x.__dict__, "boundary_points": [PointKinematics("tip", p, np.eye(3), trusted=False)]})
        out = f(x)
        assert out.ok
        p = p + DT * out.qdot
    assert 10.0 - np.linalg.norm(p) == pytest.approx(0.5, abs=0.01)
    trusted = f(inputs(p, [0.0, 0.0, -5.0], fallback=fallback))  # trusted: the model's 12 mm counts
    assert trusted.qdot[2] == pytest.approx(-5.0, rel=0.01)


def test_an_untrusted_shaft_point_far_inside_the_model_is_held_by_the_fallback():
    """The same for a point the filter may leave out of the QP (not tip or port): rows are
    left out by the tighter clearance, not by the model's. The model is 4 mm away, beyond
    what the barrier can close in a step (20 mm/s / 20 /s = 1 mm); the fallback is at the
    margin, so a push stops there."""
    fallback = Sphere(np.zeros(3), 10.0)
    p = np.array([0.0, 0.0, -9.5])  # 0.5 mm inside the fallback: at d_safe
    tip = PointKinematics("tip", np.array([0.0, 0.0, -2.0]), np.eye(3))
    x = inputs(p, [0.0, 0.0, -5.0], fallback=fallback, model=Sphere(np.zeros(3), 14.0))
    x = FilterInputs(**{**x.__dict__, "boundary_points": [tip, PointKinematics("shaft1", p, np.eye(3), trusted=False)]})
    out = SafetyFilter(NO_CALIBRATION)(x)
    assert out.ok and out.qdot[2] == pytest.approx(0.0, abs=1e-6)
    assert "boundary:shaft1" in out.active


def test_pruned_rows_do_not_change_the_answer():
    """Shaft points far from every bound are left out of the QP: same qdot as with the
    rows forced in (a model without the cheap bound)."""

    class NoBound:
        def __init__(self, s):
            self.s = s

        def signed_distance_and_gradient(self, P):
            return self.s.signed_distance(P), self.s.gradient(P)

    rng = np.random.default_rng(1)
    for _ in range(20):
        p = rng.uniform(-6, 6, 3)
        extra = [PointKinematics(f"shaft{k}", p * (1 - 0.1 * k), np.eye(3) * (1 - 0.1 * k)) for k in range(1, 4)]
        a = inputs(p, rng.uniform(-15, 15, 3))
        a = FilterInputs(**{**a.__dict__, "boundary_points": a.boundary_points + extra})
        b = FilterInputs(**{**a.__dict__, "model": NoBound(EYE)})
        np.testing.assert_allclose(SafetyFilter(NO_CALIBRATION)(a).qdot, SafetyFilter(NO_CALIBRATION)(b).qdot, atol=1e-9)


def test_non_finite_points_are_named_by_the_compiled_step():
    x = inputs([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    bad = FilterInputs(**{**x.__dict__, "boundary_points": [PointKinematics("tip", np.array([np.nan, 0.0, 0.0]),
                                                                            np.eye(3))]})
    out = SafetyFilter(NO_CALIBRATION)(bad)
    assert not out.ok and out.reason == "non-finite kinematics of tip" and not out.qdot.any()


def test_a_recovery_the_other_rules_forbid_holds_the_point_instead_of_stopping():
    """The tip 0.2 mm from the wall (inside its 0.5 mm margin: its barrier asks it back at
    the recovery rate, 5 mm/s) while an equality row pins the joint that moves it off the
    wall (z): no velocity meets both, so the step holds the tip (no closer, along z 0) and
    follows the command along x."""
    f = SafetyFilter(NO_CALIBRATION)
    p = [0.0, 0.0, -11.8]
    pinned = inputs(p, [3.0, 0.0, 0.0], rcm_A=np.array([[0.0, 0.0, 1.0]]), rcm_b=np.array([0.0]))
    out = f(pinned)
    assert out.ok and out.reason == "recovery held" and out.active[0] == "recovery held" and out.intervened
    assert abs(out.qdot[2]) <= 1e-9  # no closer to the wall (and no further: the equality)
    assert out.qdot[0] == pytest.approx(3.0, rel=0.01)  # the rest of the command
    free = f(inputs(p, [3.0, 0.0, 0.0]))
    assert free.ok and free.reason == "ok" and free.qdot[2] > 0.0  # without the pin it recovers


def test_a_state_no_hold_fixes_stops():
    """A joint below its lower limit (its bounds ask it back: zero velocity is not allowed)
    that an equality row pins: holding the recovery rows does not help, the filter stops."""
    f = SafetyFilter(NO_CALIBRATION)
    x = inputs([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], rcm_A=np.array([[1.0, 0.0, 0.0]]), rcm_b=np.array([0.0]))
    out = f(dataclasses.replace(x, q_min=np.array([1.0, -50.0, -50.0])))  # x 1 rad below its limit
    assert not out.ok and out.reason.startswith("QP: infeasible") and not out.qdot.any()


def test_a_step_the_solver_finishes_names_its_rows_as_the_full_list_does():
    """RowNames names a row when asked: each name, a slice and the whole sequence equal the
    eager list's (ConstraintStack.row_names), and the active rows of a solved step are named."""
    f = SafetyFilter(NO_CALIBRATION)
    tip = PointKinematics("tip", np.array([0.0, 0.0, -11.4]), np.eye(3))  # 0.1 mm past the margin
    shaft = PointKinematics("shaft1", np.array([0.0, 1.0, -11.0]), np.eye(3))
    x = inputs([0.0, 0.0, -11.4], [0.0, 0.0, -5.0])
    x = FilterInputs(**{**x.__dict__, "boundary_points": [tip, shaft]})
    out, stack, r, ranges = f._run(x)
    assert out.ok and "boundary:tip" in out.active
    m = int(r[4])
    ids = stack.ws[6][:m].copy()
    eager = stack.row_names(ids, ranges)
    lazy = RowNames(stack, ids, ranges)
    assert len(lazy) == len(eager) == m > 2
    assert tuple(lazy) == eager and lazy[1:3] == eager[1:3] and lazy[-1] == eager[-1]
