"""The ellipsoid's sd far from the data under the local model (models.adaptive.global_sd)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from eval.experiments.paper import run_shape
from models import Sphere
from models.adaptive.extrapolation import largest_gaps
from models.adaptive.global_sd import CREDIBLE_LOSS_RATIO, GAP_SD_SHARE, GlobalSd
from models.eyes.eye import ANTERIOR_CROP_MM
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM, IncrementalEllipsoidFit


def _posterior_cap_scatter(radius_mm: float):
    """The scatter matrix (and its origin) of points on the posterior cap (z < -6 mm) of a
    sphere about the origin: the retina's anterior direction is then +z."""
    rng = np.random.default_rng(0)
    U = rng.normal(size=(4000, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    P = radius_mm * U[U[:, 2] * radius_mm < -6.0]
    fit = IncrementalEllipsoidFit()
    fit.add(P)
    return fit.S, fit.p0


def test_largest_gaps_of_concentric_spheres():
    """A 12 mm globe against a concentric 11 mm sphere: 1 mm everywhere (exact); against a
    13 mm one as a quadric: its Sampson distance, (13^2 - 12^2) / (2 x 12) = 25/24 mm."""
    S, p0 = _posterior_cap_scatter(12.0)
    args = (S, np.zeros(3), np.full(3, 12.0), np.eye(3), p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM)
    U = np.random.default_rng(1).normal(size=(2000, 3))
    other = IncrementalEllipsoidFit()  # the 13 mm sphere as a quadric in the fits' scaled coordinates, fitted exactly
    other.add(13.0 * U / np.linalg.norm(U, axis=1, keepdims=True))
    to_sphere, to_other = largest_gaps(*args, Sphere(np.zeros(3), 11.0), other.fit().v, other.p0)
    assert to_sphere == pytest.approx(1.0, abs=1e-9)
    assert to_other == pytest.approx(25.0 / 24.0, abs=1e-9)
    assert largest_gaps(*args, Sphere(np.zeros(3), 12.0)) == (pytest.approx(0.0, abs=1e-9), 0.0)


def test_largest_gaps_leave_out_the_anterior_cap():
    """A sphere shifted 2 mm along -z (away from the front, +z) is farthest from the globe
    at the anterior pole, but the retina ends 5 mm short of it: over the grid's directions
    (u_z = -1 + (i + 1/2) / 6) the largest gap is at the posterior ring nearest the pole,
    u_z = -11/12, |12 - sqrt(144 + 4 - 48 x 11/12)| = 12 - sqrt(104) mm; the anterior ring
    (u_z = +11/12, sqrt(192) - 12 = 1.86 mm) is left out."""
    S, p0 = _posterior_cap_scatter(12.0)
    args = (S, np.zeros(3), np.full(3, 12.0), np.eye(3), p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM)
    gap, _ = largest_gaps(*args, Sphere(np.array([0.0, 0.0, -2.0]), 12.0))
    assert gap == pytest.approx(12.0 - np.sqrt(104.0), abs=1e-9)


def _globe(short: float, held: float):
    return SimpleNamespace(loss_mm2=1.0, rival_loss_mm2=short, held_loss_mm2=1.0, held_rival_loss_mm2=held)


@pytest.mark.parametrize("short, held, credible", [
    (1.0, 1.0, True), (0.99 * CREDIBLE_LOSS_RATIO, 0.99 * CREDIBLE_LOSS_RATIO, True),
    (CREDIBLE_LOSS_RATIO, 1.0, False), (1.0, CREDIBLE_LOSS_RATIO, False), (np.nan, np.nan, True),
])
def test_the_sphere_is_a_rival_while_its_loss_is_within_the_ratio_over_both_memories(short, held, credible):
    assert GlobalSd.sphere_credible(_globe(short, held)) is credible


def test_the_sd_is_the_larger_of_the_leverage_and_half_the_rivals_gap():
    sd = GlobalSd()
    assert sd.of_least_squares(_globe(1.0, 1.0)) is None  # before the globe's first fit: the ellipsoid's own
    sd.fit, sd.leverage_mm = object(), 0.2
    sd.globe_to_sphere_mm, sd.ls_to_sphere_mm, sd.ls_to_globe_mm = 1.0, 3.0, 0.6
    assert sd.of_globe(_globe(1.0, 1.0)) == GAP_SD_SHARE * 1.0
    assert sd.of_globe(_globe(10.0, 10.0)) == 0.2  # the sphere ruled out: the leverage alone
    assert sd.of_least_squares(_globe(1.0, 1.0)) == GAP_SD_SHARE * 3.0
    assert sd.of_least_squares(_globe(10.0, 1.0)) == GAP_SD_SHARE * 0.6  # the robust globe stays a rival


def test_the_staphylomas_drawn_out_globe_is_not_trusted_beyond_its_gap():
    """The paper's spiral on the staphyloma (seed 0): the robust globe taken at ~64 % is drawn
    out towards the pouch and lies up to 2.7 mm beyond the retina in front of the equator,
    where its leverage sd is 0.65 mm; with its gap from the sphere, still a rival, in its
    sd, no reference sample along the spiral lies beyond 3 sigma on the unsafe side (with
    the leverage alone 5.3 % did, by up to 0.71 mm)."""
    run = run_shape("staphyloma", seed=0, grid=60, n_curve=60, criteria=("predictive",))
    has = np.isfinite(run.lc_unsafe_curve)
    assert has.sum() > 50
    assert np.max(run.lc_unsafe_curve[has]) == 0.0 and np.max(run.lc_excess_curve[has]) < 0.0


def test_a_young_least_squares_ellipsoid_is_not_trusted_to_the_eyes_03_mm():
    """The paper's spiral on the emmetropic eye (seed 1): the criteria take the least-squares
    ellipsoid at ~17 % of the spiral, when it is still far from the retina beyond the data;
    with its gaps from the sphere (still a rival then) and the robust globe in its sd, the
    local field's 3-sigma coverage meets the target (>= 0.99) at every point of the spiral
    from then on (with the ellipsoid's fixed 0.3 mm: 0.668 right after the transition)."""
    run = run_shape("emmetropic", seed=1, grid=60, n_curve=100, criteria=("predictive",))
    after = run.fractions >= run.transitions["predictive"]
    assert after.sum() > 70
    assert np.min(run.lc_coverage_curve[after]) >= 0.99
