"""Command sources: tip paths, velocity replay and the seeded adversary."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from eval.experiments.command_sources import (ADVERSARY_MODES, AdversarialCommand, PacedTipPath, TipPathCommand,
                                             VelocityReplayCommand)

C = np.array([100.0, 0.0, 80.0])
LENS = C + [0.0, 0.0, 7.8]


def test_a_tip_path_commands_its_velocity_plus_position_feedback():
    P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    cmd = TipPathCommand([0.0, 0.5, 1.5], P, gain_per_s=10.0)
    v, roll = cmd(0.25, [0.5, 0.0, 0.0], None)
    np.testing.assert_allclose(v, [2.0, 0.0, 0.0])  # on the path: feed-forward only
    v, _ = cmd(0.25, [0.5, 0.1, 0.0], None)
    np.testing.assert_allclose(v, [2.0, -1.0, 0.0])  # 0.1 mm off: 10/s x 0.1 mm back
    v, _ = cmd(3.0, [1.0, 2.0, 0.0], None)
    np.testing.assert_allclose(v, 0.0)  # after the end: hold the last point
    assert [cmd.path_fraction(t) for t in (-1.0, 0.75, 3.0)] == [0.0, 0.5, 1.0]  # the path's time is the call's
    with pytest.raises(ValueError, match="increasing"):
        TipPathCommand([0.0, 0.0], P[:2])


def test_velocity_replay_holds_each_sample():
    cmd = VelocityReplayCommand([0.0, 0.1], [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    np.testing.assert_allclose(cmd(0.05, None, None)[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(cmd(0.15, None, None)[0], [0.0, 2.0, 0.0])
    np.testing.assert_allclose(cmd(0.25, None, None)[0], 0.0)  # past the last sample + its period


@given(st.integers(0, 10_000))
def test_the_adversary_is_seeded_bounded_and_starts_with_a_push(seed):
    a, b = (AdversarialCommand(seed, C, LENS, max_speed_mm_s=20.0) for _ in range(2))
    p = C + [0.0, 0.0, -8.0]
    for t in np.arange(0.0, 0.6, 0.001):
        va, ra = a(t, p, None)
        vb, rb = b(t, p, None)
        assert np.array_equal(va, vb) and ra == rb
        assert 10.0 - 1e-9 <= np.linalg.norm(va) <= 20.0 + 1e-9
    assert a.mode_log[0][1] == "push"
    v0 = AdversarialCommand(seed, C, LENS)(0.0, p, None)[0]
    assert v0 @ (p - C) / (np.linalg.norm(v0) * 8.0) > np.cos(np.radians(45.0))  # toward the retina


def test_adversary_bad_arguments():
    with pytest.raises(ValueError, match="modes"):
        AdversarialCommand(0, C, LENS, modes=("dance",))
    with pytest.raises(ValueError, match="segment_s"):
        AdversarialCommand(0, C, LENS, segment_s=(0.2, 0.1))
    assert set(ADVERSARY_MODES) == {"push", "along", "port_side", "lens", "random"}


def _tip_path_reference(cmd: TipPathCommand, roll_rad: np.ndarray, t_s: float, p_WT) -> tuple[np.ndarray, float]:
    """The tip path's command written straight from its definition, in NumPy: the segment's
    velocity (zero outside the path) plus the capped feedback to np.interp's reference."""
    t, P = cmd.times_s, cmd.P_WT
    k = int(np.searchsorted(t, t_s, side="right")) - 1
    inside = 0 <= k < len(t) - 1
    v_ff = (P[k + 1] - P[k]) / (t[k + 1] - t[k]) if inside else np.zeros(3)
    roll = (roll_rad[k + 1] - roll_rad[k]) / (t[k + 1] - t[k]) if inside else 0.0
    fb = cmd.gain_per_s * (np.array([np.interp(t_s, t, P[:, i]) for i in range(3)]) - p_WT)
    n = np.linalg.norm(fb)
    return v_ff + (fb if n <= cmd.max_feedback_mm_s else fb * cmd.max_feedback_mm_s / n), roll


@given(st.integers(0, 10_000))
def test_the_tip_path_command_matches_its_numpy_reference_at_random_times(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(2, 40))
    t = np.cumsum(rng.uniform(0.01, 0.2, m)) - 0.1
    P = 100.0 + rng.normal(0.0, 2.0, (m, 3))  # segments below ~1,000 mm/s
    roll = rng.uniform(-3.0, 3.0, m)
    cmd = TipPathCommand(t, P, roll_rad=roll, gain_per_s=rng.uniform(1.0, 50.0), max_feedback_mm_s=rng.uniform(0.5, 20.0))
    times = np.concatenate([rng.uniform(t[0] - 0.5, t[-1] + 0.5, 50), t])  # the knots themselves too
    for t_s in times:
        p = P[rng.integers(m)] + rng.normal(0.0, rng.choice([1e-3, 0.1, 2.0]), 3)
        v, r = cmd(t_s, p, None)
        v_ref, r_ref = _tip_path_reference(cmd, roll, t_s, p)
        # the same arithmetic up to rounding: |v| < ~1,000 mm/s, whose ulp is 1.1e-13 mm/s
        np.testing.assert_allclose(v, v_ref, rtol=0.0, atol=1e-12)
        assert abs(r - r_ref) <= 1e-12
        np.testing.assert_allclose(cmd.reference(t_s), [np.interp(t_s, t, P[:, i]) for i in range(3)], rtol=0, atol=1e-12)


@given(st.integers(0, 10_000))
def test_a_paced_path_followed_closely_is_its_timed_path(seed):
    """A tip that stays within free_mm of the reference keeps the clock at full pace: the
    paced path then commands what the timed path does at the same time."""
    rng = np.random.default_rng(seed)
    m = int(rng.integers(2, 20))
    t = np.cumsum(rng.uniform(0.01, 0.2, m))
    P = 100.0 + np.cumsum(rng.normal(0.0, 0.5, (m, 3)), axis=0)
    roll = rng.uniform(-3.0, 3.0, m)
    timed, paced = TipPathCommand(t, P, roll_rad=roll), PacedTipPath(t, P, roll_rad=roll)
    paced.path_time_s = t[0]
    for t_s in np.arange(t[0], t[-1], 0.001):
        p = paced.reference(paced.path_time_s) + rng.uniform(-1.0, 1.0, 3) * 0.99 * paced.free_mm / np.sqrt(3.0)
        v, r = paced(t_s, p, None)
        v_ref, r_ref = timed(t_s, p, None)
        assert abs(paced.path_time_s - t_s) <= 1e-9 and not paced.finished
        np.testing.assert_allclose(v, v_ref, rtol=0.0, atol=1e-9)
        assert abs(r - r_ref) <= 1e-9


def test_a_held_tip_slows_the_paced_clock_to_its_floor_and_the_path_ends_after_settling():
    """A 10 mm path at 10 mm/s with the tip held at its start: the clock runs at full pace
    while the reference is within free_mm (0.05 s), then slows, at the floor from hold_mm on
    (2 mm); the path is finished settle_s after its clock's end, the tip still held."""
    P = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    cmd = PacedTipPath([0.0, 1.0], P, roll_rad=[0.0, 1.0])
    assert (cmd.free_mm, cmd.hold_mm, cmd.floor, cmd.settle_s) == (0.5, 2.0, 0.25, 0.4)
    dt, t_s, rates, lags = 0.001, 0.0, [], []
    while not cmd.finished and t_s < 10.0:
        before = cmd.path_time_s
        v, roll = cmd(t_s, P[0], None)
        if 0.0 < t_s and cmd.path_time_s < 1.0:  # the clock's end clips its last step
            lags.append(10.0 * before)  # mm: the reference's distance from the held tip
            rates.append((cmd.path_time_s - before) / dt)
        t_s += dt
    rates, lags = np.array(rates), np.array(lags)
    np.testing.assert_allclose(rates[lags <= 0.5], 1.0, atol=1e-9)
    np.testing.assert_allclose(rates[lags >= 2.0], 0.25, atol=1e-9)
    mid = (lags > 0.5) & (lags < 2.0)
    np.testing.assert_allclose(rates[mid], 1.0 - 0.75 * (lags[mid] - 0.5) / 1.5, atol=1e-9)
    # the clock: 0.05 s to 0.5 mm, the slowing to 2 mm (1.5 mm at between the floor's 2.5 mm/s and 10 mm/s:
    # 0.15-0.6 s), the rest (8 mm) at 2.5 mm/s: 3.2 s; finished 0.4 s later
    t_end = cmd._calls_t[int(np.argmax(np.array(cmd._calls_path) >= 1.0))]
    assert 3.2 + 0.05 + 0.15 < t_end < 3.2 + 0.05 + 0.6
    assert cmd.finished and t_end + 0.4 - 1e-9 <= cmd._t_last <= t_end + 0.4 + dt + 1e-9
    assert cmd.path_fraction(t_end) == 1.0 and 0.0 < cmd.path_fraction(1.0) < 0.5
    # at the floor the feed-forward is a quarter of the path's (10 mm/s) plus the capped feedback (10 mm/s)
    held = PacedTipPath([0.0, 1.0], P, roll_rad=[0.0, 1.0])
    held(0.0, P[0], None)
    held.path_time_s = 0.5  # the reference 5 mm ahead
    v, roll = held(0.001, P[0], None)
    np.testing.assert_allclose(v, [2.5 + 10.0, 0.0, 0.0], atol=1e-9)
    assert abs(roll - 0.25) <= 1e-12


def test_a_paced_path_is_finished_once_the_tip_reaches_its_end():
    P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cmd = PacedTipPath([0.0, 0.1], P)
    for t_s in np.arange(0.0, 0.2, 0.001):
        cmd(t_s, cmd.reference(cmd.path_time_s), None)
        if cmd.finished:
            break
    assert cmd.finished and 0.1 <= t_s <= 0.1 + 0.0021  # the step after the clock's end


@pytest.mark.parametrize("kwargs, match", [({"floor": 0.0}, "floor"), ({"floor": 1.5}, "floor"),
                                           ({"free_mm": 2.0, "hold_mm": 1.0}, "free_mm and hold_mm"),
                                           ({"settle_s": -1.0}, "settle_s")])
def test_paced_path_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PacedTipPath([0.0, 1.0], np.zeros((2, 3)) + [[0.0, 0, 0], [1.0, 0, 0]], **kwargs)
