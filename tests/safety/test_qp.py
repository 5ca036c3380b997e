"""The filter's dense QP: the direct DAQP call and the no-solver shortcut against Clarabel."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safety.constraints.tip_speed import FACE_NORMALS, REACH
from safety.qp import DenseQP, solve


def random_filter_qp(seed: int, clearance_mm: float, v_cmd=(3.0, 1.0, -2.0)) -> DenseQP:
    """Filter-shaped (the rows safety.constraints write): 6 joints, tracking cost with damping
    1e-3, joint bounds, the tip speed polytope at 20 mm/s, 8 barrier rows at `clearance_mm`
    (h_min 0.5 mm, gain 20/s), two RCM rows; random Jacobians."""
    rng = np.random.default_rng(seed)
    n, k = 6, 8
    J = 50.0 * rng.normal(size=(3, n))
    J_roll = rng.normal(size=(1, n))
    H = 2.0 * (J.T @ J + J_roll.T @ J_roll + 1e-3 * np.eye(n))
    c = -2.0 * (J.T @ np.asarray(v_cmd) + J_roll.T @ [0.1])
    g = rng.normal(size=(k, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    J_pts = 50.0 * rng.normal(size=(k, 3, n))
    G = np.vstack([FACE_NORMALS @ J, -np.einsum("ki,kij->kj", g, J_pts)])
    h = np.concatenate([np.full(len(FACE_NORMALS), 20.0 / REACH), np.maximum(20.0 * (clearance_mm - 0.5), -5.0)
                        * np.ones(k)])
    bound = np.minimum(3.0, 10.0 * (2.0 - 0.03))
    names = ("tip_speed",) * len(FACE_NORMALS) + tuple(f"b{i}" for i in range(k))
    return DenseQP(H, c, np.full(n, -bound), np.full(n, bound), G, h, rng.normal(size=(2, n)), np.zeros(2), names)


@settings(max_examples=40)
@given(seed=st.integers(0, 2**32 - 1), clearance=st.floats(0.3, 5.0))
def test_daqp_direct_and_the_shortcut_agree_with_clarabel(seed, clearance):
    # both solve the same convex QP: equal to the solvers' tolerance, whether rows are active
    # (near the margin) or not (far). Clarabel stops at a relative duality gap of 1e-8; along
    # the directions only the damping curves (Hessian eigenvalue 2e-3), a gap of that size
    # leaves x off by up to sqrt(2 gap / 2e-3) ~ 1e-5 rad/s (seed 181439: 1.2e-6)
    # (random rows can make a QP infeasible: then both must say so)
    qp = random_filter_qp(seed, clearance)
    ours, ref = solve(qp, "daqp"), solve(qp, "clarabel")
    assert ours.ok == ref.ok
    if not ref.ok:
        return
    np.testing.assert_allclose(ours.x, ref.x, atol=1e-5)
    assert np.all(qp.G @ ours.x <= qp.h + 1e-7 * (1 + np.abs(qp.h)))
    np.testing.assert_allclose(qp.A @ ours.x, qp.b, atol=1e-8)


def test_active_rows_are_named():
    # far from every bound, nothing is active; a tip command 3x the speed limit activates the polytope
    assert solve(random_filter_qp(0, 50.0, v_cmd=(0.1, 0.0, 0.0))).active == ()
    assert "tip_speed" in solve(random_filter_qp(0, 50.0, v_cmd=(60.0, 0.0, 0.0))).active


@pytest.mark.parametrize("solver", ["daqp", "clarabel"])
def test_failures_are_values_with_reasons(solver):
    qp = random_filter_qp(1, 1.0)
    assert solve(qp._replace(c=np.full(6, np.nan)), solver).reason == "non-finite QP data"
    assert solve(qp._replace(lb=np.full(6, 1.0), ub=np.zeros(6)), solver).reason == "infeasible: bounds cross"
    # x_1 >= 1 rad/s and x_1 <= -1 rad/s as two rows: infeasible
    G = np.zeros((2, 6))
    G[0, 0], G[1, 0] = -1.0, 1.0
    infeasible = qp._replace(G=G, h=np.array([-1.0, -1.0]), row_names=("a", "b"))
    out = solve(infeasible, solver)
    assert out.x is None and out.reason == "infeasible or not solved"
