"""The sensor's compiled packet kernels: the true and calibrated beams of M samples, the
true retina along the true beams, and the "distance" mode's whole packet.

The sensor's latches hold the joint angles over several samples, so a packet's rows of
joint angles come in runs of equal rows (`row_runs`): the chain is evaluated, and the
ray cast, once per run. Both modes take a packet's geometry from `packet_geometry` and
its points from `beam_points`; they differ only in how a distance is extracted from a
beam ("ascan": synthesis and segmentation, in IioctSensor; "distance": the extractor's
error model, `distance_packet`).

Units: mm, rad; frame W.
"""
from __future__ import annotations

import numba
import numpy as np

from models.eyes import retina_hits
from models.iioct.error_model import draw_one
from planning.chain import chain_pose_into, frame_axis_into

DISTANCE_MODE_CONFIDENCE = 0.9  # of a valid "distance" mode sample
DISTANCE_REASONS = ("", "no_retina", "low_confidence")  # the reasons of `distance_packet`'s codes
NO_RETINA, LOW_CONFIDENCE = 1, 2  # their codes
BEAM_AXIS = 2  # the beam is the sensor frame's z axis


@numba.njit(cache=True)
def _same_row(A, m, B, k) -> bool:
    """Whether row m of A equals row k of B (rows of joint angles; NaN equals nothing,
    -0.0 equals 0.0)."""
    for i in range(A.shape[1]):
        if A[m, i] != B[k, i]:
            return False
    return True


@numba.njit(cache=True)
def row_runs(Q):
    """(starts (n,), run (M,)) of the rows of Q (M, k): the first row of each of the n
    runs of equal consecutive rows (NaN equals nothing, -0.0 equals 0.0) and the run
    of each row; row m starts its run where starts[run[m]] == m."""
    M = Q.shape[0]
    starts, run = np.empty(M, dtype=np.int64), np.empty(M, dtype=np.int64)
    n = 0
    for m in range(M):
        if m == 0 or not _same_row(Q, m, Q, m - 1):
            starts[n] = m
            n += 1
        run[m] = n - 1
    return starts[:n], run


@numba.njit(cache=True)
def _beams(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported, runs_true, runs_reported):
    """`sensor_beams` with the row runs (`row_runs`) of Q_true and Q_reported given."""
    (starts, run), (starts_r, run_r) = runs_true, runs_reported
    M = Q_true.shape[0]
    O_true, U_true, O_cal, U_cal = np.empty((M, 3)), np.empty((M, 3)), np.empty((M, 3)), np.empty((M, 3))
    R, p, R_rep, p_rep, work = np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(3), np.empty((2, 3, 3))
    for m in range(M):
        if starts[run[m]] == m:
            chain_pose_into(S, Q_true[m], R, p, work)
            frame_axis_into(R, p, R_true, p_true, BEAM_AXIS, O_true, U_true, m)
        else:  # (R, p) stays the product at this row
            O_true[m], U_true[m] = O_true[m - 1], U_true[m - 1]
        if starts_r[run_r[m]] != m:
            O_cal[m], U_cal[m] = O_cal[m - 1], U_cal[m - 1]
        elif _same_row(Q_reported, m, Q_true, m):
            frame_axis_into(R, p, R_cal, p_cal, BEAM_AXIS, O_cal, U_cal, m)
        else:
            chain_pose_into(S, Q_reported[m], R_rep, p_rep, work)
            frame_axis_into(R_rep, p_rep, R_cal, p_cal, BEAM_AXIS, O_cal, U_cal, m)
    return O_true, U_true, O_cal, U_cal


@numba.njit(cache=True)
def sensor_beams(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported):
    """(O_true, U_true, O_cal, U_cal), each (M, 3) in W: the origins (mm) and z axes of
    the chain's (planning.chain, screw axes S) frames with home poses (R_true, p_true) at
    the rows of Q_true and (R_cal, p_cal) at the rows of Q_reported (M, n) rad: the true
    and the calibrated beams. The chain is evaluated once per run of equal rows
    (`row_runs`) of each, not at all for a reported row equal to its true one; equal
    angles give equal beams bit for bit (signed zeros too: an angle of -0.0 or 0.0 gives
    the same product)."""
    return _beams(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported, row_runs(Q_true), row_runs(Q_reported))


@numba.njit(cache=True)
def packet_geometry(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported, eye, max_distance_mm):
    """(O_cal, U_cal (M, 3): the calibrated beams (`sensor_beams`); d_true (M,) mm: the
    distance along the true beam to the true retina, NaN without a hit; incidence (M,)
    rad at the hit, NaN without one; live (M,) bool: a retina within max_distance_mm)
    of M samples at the joint angles Q_true and Q_reported (M, n) rad. The retina from
    models.eyes.retina_hits with the eye's `Eye.hit_arguments` `eye`, one ray cast per
    run of equal rows of Q_true. ValueError as retina_hits."""
    runs = row_runs(Q_true)
    O_true, U_true, O, U = _beams(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported, runs, row_runs(Q_reported))
    starts, run = runs
    hit_distance, hit_incidence = retina_hits(O_true[starts], U_true[starts], *eye)
    d_true, incidence = hit_distance[run], hit_incidence[run]
    live = np.empty(len(d_true), dtype=np.bool_)
    for m in range(len(d_true)):
        live[m] = d_true[m] <= max_distance_mm  # False for NaN: no hit
    return O, U, d_true, incidence, live


@numba.njit(cache=True)
def beam_points(O, U, d, valid):
    """P_W (M, 3) mm: the points O + d U at the distances d (M,) mm along the beams
    (origins O mm, unit directions U (M, 3)) where valid (M,), NaN rows elsewhere."""
    P = np.full(O.shape, np.nan)
    for m in range(O.shape[0]):
        if valid[m]:
            for k in range(3):
                P[m, k] = O[m, k] + d[m] * U[m, k]
    return P


@numba.njit(cache=True)
def distance_packet(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported, eye, max_distance_mm, D, A, tables,
                    uniform, normal, floater_rate, floater_draws):
    """The arrays of a "distance" mode packet of M samples in one compiled pass: the
    geometry at Q_true and Q_reported (M, 6) rad (`packet_geometry`, chain S, homes
    (R_true, p_true) and (R_cal, p_cal), eye `eye`); a sample with no retina within
    max_distance_mm (mm) is invalid ("no_retina"), the others get the error model's
    draw (`draw_one` with ExtractorErrorModel.grid's D mm, A rad and `tables`) from
    uniform[m] and normal[m] (M,); then, with floater_rate > 0, a floater where
    floater_draws[0, m] < floater_rate on a beam longer than 1 mm: a valid distance
    0.5 + (d_true - 1) floater_draws[1, m] mm, uniform between 0.5 mm and 0.5 mm before
    the retina (floater_draws: (2, M) uniforms in [0, 1), not read without floaters).

    Returns (d (M,) mm, NaN where invalid; valid (M,) bool; confidence (M,)
    (DISTANCE_MODE_CONFIDENCE where valid, else 0); codes (M,) uint8, the indices of the
    samples' reasons in DISTANCE_REASONS; P_W (M, 3) mm (`beam_points`); O_cal, U_cal
    (M, 3) the calibrated beams; d_true (M,) mm, NaN without a hit). ValueError when the
    draws do not have M samples, or as retina_hits."""
    M = Q_true.shape[0]
    if len(uniform) != M or len(normal) != M or (floater_rate > 0.0 and floater_draws.shape[1] != M):
        raise ValueError("uniform and normal must be (M,) draws, and floater_draws (2, M) with floaters")
    O, U, d_true, incidence, live = packet_geometry(S, R_true, p_true, R_cal, p_cal, Q_true, Q_reported, eye,
                                                    max_distance_mm)
    d, valid, confidence = np.full(M, np.nan), np.zeros(M, dtype=np.bool_), np.zeros(M)
    codes = np.zeros(M, dtype=np.uint8)
    for m in range(M):
        if not live[m]:
            codes[m] = NO_RETINA
            continue
        d[m], valid[m] = draw_one(D, A, tables, d_true[m], incidence[m], uniform[m], normal[m])
        if floater_rate > 0.0 and floater_draws[0, m] < floater_rate and d_true[m] > 1.0:
            d[m], valid[m] = 0.5 + (d_true[m] - 1.0) * floater_draws[1, m], True
        if valid[m]:
            confidence[m] = DISTANCE_MODE_CONFIDENCE
        else:
            codes[m] = LOW_CONFIDENCE
    return d, valid, confidence, codes, beam_points(O, U, d, valid), O, U, d_true


@numba.njit(cache=True)
def all_finite(A, B) -> bool:
    """Whether every entry of A and B is finite."""
    for X in (A, B):
        for x in X.flat:
            if not np.isfinite(x):
                return False
    return True
