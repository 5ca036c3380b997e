"""A step with no velocity is solved again in its relaxed forms (safety.stack): recovery
held, then the RCM's drift correction halved and dropped; only what no form solves stops.

The toy: three joints that translate the instrument (J = I for the tip and the trocar
point), the shaft along x (R_WI = I: the RCM's rows are the y and z velocities), the
trocar 0.1 mm off the shaft along y, corrected at 50/s: the RCM asks 5 mm/s along y. The
tip's wall lies along +y (moving along -y raises its clearance h): its barrier allows
qdot_y <= 20 (h - 0.5) mm/s, capped at -5 mm/s of recovery below the margin.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from safety import ConstraintStack, FilterConfig
from safety.constraints import JointPositionLimits, JointSpeedLimits, LinearEquality, PointBarrier, RcmEquality
from safety.stack import CORRECTION_EASED, EASED_SCALES, RECOVERY_HELD, relaxations
from safety.tabulated_field import tabulate, tabulated_kernel

GAIN, ERROR = 50.0, 0.1  # 1/s, mm: the RCM asks GAIN x ERROR = 5 mm/s along y
BARRIER = PointBarrier("boundary", "eye", d_safe_mm=0.5, gain_per_s=20.0, max_recovery_mm_s=5.0, always_first=1)
CONFIG = FilterConfig(calibration_bound_mm=0.0, calibration_bound_deg=0.0)


def step(h_mm: float, equality=None, extra=(), normal=(0.0, -1.0, 0.0), error=(ERROR, 0.0)):
    """The filter's step on the toy with the tip at clearance h_mm (the field's gradient
    `normal`), the trocar `error` (y, z) mm off the shaft, commanded 3 mm/s along x."""
    if equality is None:
        equality = RcmEquality(np.array([0.0, error[0], error[1]]), GAIN, group="trocar")
    groups = {"boundary": 1, "trocar": 1}
    stack = ConstraintStack([BARRIER, equality, *extra], groups, {"eye": tabulated_kernel}, CONFIG, n_joints=3)
    P, J = np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1))
    table = tabulate([h_mm], [normal], [0.0])
    out, _ = stack.solve(np.zeros(3), np.array([3.0, 0.0, 0.0, 0.0]), np.zeros(3), np.eye(3), np.zeros((0, 3)), P, J,
                         np.array([[0, 1], [1, 2]]), (table,))
    return out


def test_a_step_with_room_for_the_whole_correction_is_not_touched():
    out = step(2.0)  # the barrier allows 30 mm/s along y
    assert out.ok and out.reason == "ok" and relaxations(out.reason) == ()
    assert out.qdot[1] == pytest.approx(GAIN * ERROR, abs=1e-6) and out.qdot[2] == pytest.approx(0.0, abs=1e-6)


def test_a_correction_the_barrier_forbids_is_halved():
    """h = 0.65 mm: the barrier allows 3 mm/s along y, the RCM asks 5; no row recovers (no
    held form). Half the correction (2.5 mm/s) fits: the shaft still pivots (z 0), the
    command along x is followed."""
    out = step(0.65)
    assert out.ok and out.reason == CORRECTION_EASED and out.active[0] == CORRECTION_EASED and out.intervened
    assert out.qdot[1] == pytest.approx(0.5 * GAIN * ERROR, abs=1e-6)
    assert out.qdot[2] == pytest.approx(0.0, abs=1e-9)
    assert out.qdot[0] == pytest.approx(3.0, rel=0.01)


def test_a_recovering_tip_against_the_correction_holds_and_drops_it():
    """h = 0.4 mm: the tip recovers (qdot_y <= -2 mm/s), the RCM asks +5. Held (<= 0) with
    the whole or half correction: none; the correction dropped with the recovery as asked
    (0 <= -2): none; dropped and held: qdot_y = 0."""
    out = step(0.4)
    assert out.ok and out.reason == f"{CORRECTION_EASED}, {RECOVERY_HELD}"
    assert out.active[:2] == (CORRECTION_EASED, RECOVERY_HELD)
    assert relaxations(out.reason) == (CORRECTION_EASED, RECOVERY_HELD)
    assert out.qdot[1] == pytest.approx(0.0, abs=1e-9) and out.qdot[2] == pytest.approx(0.0, abs=1e-9)


def test_a_state_no_relaxation_fixes_stops():
    """The y joint 1 rad below its limit: its bound asks it back at >= 10 rad/s, more than
    the whole correction; no form solves and the filter stops with zero velocity."""
    below = JointPositionLimits(np.array([-50.0, 1.0, -50.0]), np.full(3, 50.0), gain_per_s=10.0, margin_rad=0.0)
    out = step(2.0, extra=(below,))
    assert not out.ok and out.reason.startswith("QP: infeasible") and not out.qdot.any()


def test_an_equality_that_is_no_drift_correction_is_never_eased():
    """The same 5 mm/s along y given as a plain equality (LinearEquality: a caller's rows,
    whose right side is not known to be a correction): the barrier's 3 mm/s stops the step."""
    given = LinearEquality(np.array([[0.0, 1.0, 0.0]]), np.array([GAIN * ERROR]))
    out = step(0.65, equality=given)
    assert not out.ok and out.reason.startswith("QP: infeasible")


@settings(max_examples=60)
@given(st.floats(0.2, 1.5), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-0.2, 0.2),
       st.floats(-0.2, 0.2))
def test_the_step_is_the_first_relaxed_form_that_has_a_velocity(h, gx, gy, gz, ey, ez):
    """Any wall normal, clearance and trocar error, joint speeds within 12 rad/s: the
    filter's answer is the first of the forms (correction x1, x0.5, x0; recovery as asked,
    then held) that has a velocity (for this toy: the free x joint can make up
    |g_x| x 12 mm/s of the barrier's row), the trocar rows met at that scale exactly and the
    barrier's row as that form asks it; a stop when none has one."""
    g = np.array([gx, gy, gz])
    assume(np.linalg.norm(g) > 0.1)
    g /= np.linalg.norm(g)
    vmax = 12.0
    rhs = max(20.0 * (h - 0.5), -5.0)  # the barrier's row: -g . qdot <= rhs
    b = GAIN * np.array([ey, ez])
    forms = [(1.0, False)] + ([(1.0, True)] if rhs < 0 else [])
    if np.any(b != 0.0):
        for scale in EASED_SCALES:
            forms += [(scale, False)] + ([(scale, True)] if rhs < 0 else [])

    def slack(scale, hold):  # > 0: the form has a velocity
        return (max(rhs, 0.0) if hold else rhs) + abs(g[0]) * vmax + g[1:] @ (scale * b)

    assume(all(abs(slack(*f)) > 1e-6 for f in forms))  # away from the edges the solver's tolerance decides
    expected = next((f for f in forms if slack(*f) > 0), None)
    out = step(h, extra=(JointSpeedLimits(np.full(3, vmax)),), normal=g, error=(ey, ez))
    if expected is None:
        assert not out.ok and out.reason.startswith("QP: infeasible") and not out.qdot.any()
        return
    scale, hold = expected
    want = ((CORRECTION_EASED,) if scale < 1.0 else ()) + ((RECOVERY_HELD,) if hold else ())
    assert out.ok and relaxations(out.reason) == want and out.active[:len(want)] == want
    np.testing.assert_allclose(out.qdot[1:], scale * b, atol=1e-6)
    assert -g @ out.qdot <= (max(rhs, 0.0) if hold else rhs) + 1e-6
    assert np.all(np.abs(out.qdot) <= vmax + 1e-6)
