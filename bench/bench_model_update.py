"""Eye model figures: per-A-scan update time, the fits' small linear algebra against
np.linalg, batch fits, signed-distance throughput, and Drake's
ComputeSignedDistanceToPoint on the same ellipsoid."""
from __future__ import annotations

import gc
import time

import numpy as np
from numba import njit

from bench.timing import machine_stalls, summary_us, time_calls_us
from models import AdaptiveEyeModel, Ellipsoid, Sphere, fit_ellipsoid, fit_sphere
from models.adaptive.extrapolation import extrapolation_sd, largest_gaps
from models.adaptive.transition import PredictiveCriteria
from models.eyes import make_eye
from models.eyes.eye import ANTERIOR_CROP_MM
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.fit.eye_globe import REFIT_ITERATIONS
from models.fit.robust_fit import RobustFitConfig
from models.fit.small_linalg import cholesky, eigh_sym, lower_inverse, pivoted_solve
from models.local.field import LocalField
from models.local.grid import LocalRetinaModel
from models.realtime import collector_paused
from models.scan.paper_scan import paper_scan
from safety import FilterConfig

RADII = np.array([11.455, 11.365, 10.148])


def _update_times(points, criteria, batch: int, robust: RobustFitConfig | None = None, local: bool = False,
                  repeat: int = 1, beams=None) -> np.ndarray:
    """Per-A-scan time (us) of each update of a new model fed `points` (and their `beams`,
    as the loop gives them, when not None) in packets of `batch` (`repeat` times over), as
    a real-time stream runs it: with the cyclic garbage collector paused (models.realtime)."""
    m = AdaptiveEyeModel(criteria, robust=robust, local=LocalRetinaModel(np.zeros(3)) if local else None)
    chunks = [points[i:i + batch] for i in range(0, len(points), batch)] * repeat
    beam_chunks = ([None] * len(chunks) if beams is None
                   else [beams[i:i + batch] for i in range(0, len(beams), batch)] * repeat)
    with collector_paused():
        return time_calls_us(lambda i: m.update(chunks[i], beam_chunks[i]), len(chunks)) / batch


def collector_figures(points: np.ndarray, repeat: int = 8) -> None:
    """The update with the local part over `repeat` spirals into one model, with Python's
    cyclic garbage collector on and paused, and the collector's own passes while it is on."""
    pauses, start = {0: [], 1: [], 2: []}, [0.0]

    def watch(phase, info):
        if phase == "start":
            start[0] = time.perf_counter()
        else:
            pauses[info["generation"]].append(1e6 * (time.perf_counter() - start[0]))

    m = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
    chunks = [points[i:i + 1] for i in range(len(points))] * repeat
    gc.collect()
    gc.callbacks.append(watch)
    try:
        t_on = time_calls_us(lambda i: m.update(chunks[i]), len(chunks))
    finally:
        gc.callbacks.remove(watch)
    t_off = _update_times(points, PredictiveCriteria(), 1, local=True, repeat=repeat)
    print(f"  predictive + local, {len(chunks):,} A-scans ({repeat} spirals), collector on:     {summary_us(t_on)}")
    print(f"    its passes: " + ", ".join(f"generation {g} {len(p)} x, max {max(p, default=0.0):,.0f} us" for g, p in pauses.items()))
    print(f"  the same, collector paused (models.realtime.collector_paused):  {summary_us(t_off)}")


@njit
def _loop_cholesky(A, n, lapack):
    s = 0.0
    for _ in range(n):
        s += np.linalg.cholesky(A)[-1, -1] if lapack else cholesky(A)[0][-1, -1]
    return s


@njit
def _loop_lower_inverse(L, n, lapack):
    s = 0.0
    for _ in range(n):
        s += np.linalg.inv(L)[-1, 0] if lapack else lower_inverse(L)[-1, 0]
    return s


@njit
def _loop_solve(A, b, n, lapack):
    s = 0.0
    for _ in range(n):
        s += np.linalg.solve(A, b)[0] if lapack else pivoted_solve(A.copy(), b, 1e-300)[0]
    return s


@njit
def _loop_eigh(A, n, lapack):
    s = 0.0
    for _ in range(n):
        s += np.linalg.eigh(A)[0][0] if lapack else eigh_sym(A)[0][0]
    return s


def _per_call_us(loop, args: tuple, lapack: bool, n: int = 20000) -> float:
    """Microseconds per call in the compiled loop(*args, n, lapack): the fastest of 5 runs,
    after a warm-up that compiles it."""
    loop(*args, 10, lapack)
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        loop(*args, n, lapack)
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / n


def small_linalg_figures(points: np.ndarray) -> None:
    """The fits' hand-written small linear algebra (models.fit.small_linalg) against
    np.linalg inside numba, per call on warm compiled code, on symmetric positive definite
    matrices of the sizes the fits use, and the eigensolver on the 3x3 matrices of a fit
    of the retinal points `points` (N, 3) mm."""
    rng = np.random.default_rng(0)
    for k in (4, 6):
        B = rng.normal(size=(k, k))
        A = B @ B.T + k * np.eye(k)
        L, b = np.linalg.cholesky(A), rng.normal(size=k)
        figures = [(name, _per_call_us(loop, args, False), _per_call_us(loop, args, True)) for name, loop, args in (
            ("Cholesky", _loop_cholesky, (A,)), ("lower-triangular inverse", _loop_lower_inverse, (L,)),
            ("pivoted solve", _loop_solve, (A, b)), ("symmetric eigensolver", _loop_eigh, (A,)))]
        print(f"  small linear algebra {k}x{k}, hand-written / np.linalg per call: "
              + ", ".join(f"{name} {hand:.2f} / {lapack:.2f} us" for name, hand, lapack in figures))
    fit = fit_ellipsoid(points)  # the 3x3 matrices of a fit: its quadric's and its points' covariance
    for name, A in (("quadric", fit.rotation @ np.diag(fit.radii**-2.0) @ fit.rotation.T), ("covariance", np.cov(points.T))):
        print(f"  symmetric eigensolver on a fit's 3x3 {name}, hand-written / np.linalg.eigh per call: "
              f"{_per_call_us(_loop_eigh, (A,), False):.2f} / {_per_call_us(_loop_eigh, (A,), True):.2f} us")


def _drake_signed_distance(Q_mm: np.ndarray):
    """Drake's signed distance (mm, > 0 inside like ours) to an anchored Ellipsoid, and the
    time per point (us)."""
    from pydrake.geometry import Ellipsoid as DrakeEllipsoid
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, CoulombFriction
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(), DrakeEllipsoid(*(RADII / 1e3)), "retina", CoulombFriction(0.5, 0.5))
    plant.Finalize()
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    out = np.empty(len(Q_mm))
    t0 = time.perf_counter()
    for i, q in enumerate(Q_mm / 1e3):
        out[i] = -query.ComputeSignedDistanceToPoint(q, 1.0)[0].distance * 1e3  # Drake: < 0 inside
    return out, 1e6 * (time.perf_counter() - t0) / len(Q_mm)


def local_field_figures(points: np.ndarray) -> None:
    """The local model's field at the filter's 12 monitored points per control step."""
    m = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
    for i in range(0, len(points), 20):
        m.update(points[i:i + 20])
    f = LocalField(m.local.params(True))
    Q = points[::400][:12] * 0.95
    kernel, params = f.field_kernel()
    kernel(params, Q)
    t = time_calls_us(lambda i: kernel(params, Q), 2000)
    print(f"  local field at 12 points (one control step's tip, port, shaft):        {summary_us(t)}")
    # the barrier's form (the loop's k = 3, d_safe + calibration kept, its reach): 12 points 9 % of the radius
    # (~1 mm) inside the retina each read the directions beside it (lateral_bound); at 5 % (~0.55 mm, at the
    # boundary) their bound lies below their distance from every ray the look reads, and the look is skipped
    barrier = f.with_fallback(*FilterConfig(sigma_factor=3.0).field_bound(Sphere(np.zeros(3), 1.0)))
    kernel, params = barrier.field_kernel()
    for label, P in (("1 mm inside, each reading the look", points[::400][:12] * 0.91),
                     ("0.55 mm inside, the look skipped ", Q)):
        kernel(params, P)
        t = time_calls_us(lambda i: kernel(params, P), 2000)
        print(f"  the same in the barrier's form, {label}:    {summary_us(t)}")
    for name, model, P in (("emmetropic", m, points), ("detached", None, paper_scan(make_eye("detached"), seed=0).points)):
        if model is None:
            model = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
            for i in range(0, len(P), 20):
                model.update(P[i:i + 20])
        t = time_calls_us(lambda i: model.local.params(True), 50)
        print(f"  local field's refresh (every 5 updates), {name} eye, paper spiral:      {summary_us(t)}")
    globe, fit = model.globe, model.globe.last_ok  # the detached eye's: its sd far from the data, once per new fit
    args = (globe.last_scatter, fit.v, fit.center, fit.radii, fit.rotation, globe.p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM)
    t = time_calls_us(lambda i: extrapolation_sd(*args), 2000)
    print(f"  the robust globe's sd far from the data (extrapolation_sd), detached eye:  {summary_us(t)}")
    # its gaps from the rivals (models.adaptive.global_sd: two calls per fit, the second with another quadric)
    gap_args = (globe.last_scatter, fit.center, fit.radii, fit.rotation, globe.p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM,
                model.sphere, fit.v, globe.p0)
    t = time_calls_us(lambda i: largest_gaps(*gap_args), 2000)
    print(f"  its largest gaps from the sphere and another quadric (largest_gaps), detached eye: {summary_us(t)}")
    eye_globe_figures()


def eye_globe_figures() -> None:
    """The eye globe's refit (models.fit.eye_globe: one candidate's steps and every
    candidate's cost, every 20 points while it stands under the local model) on the pointed eye's paper spiral,
    with a wall point, and the pointed eye's update per A-scan, where it runs."""
    eye = make_eye("pointed")
    scan = paper_scan(eye, seed=0)
    wall = eye.pose.p_WE + np.array([0.0, 11.0, 5.0])  # a point of the wall in front of the equator
    times = []
    for _ in range(2):  # the first stream loads the compiled code: the second's times
        m = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(eye.pose.p_WE), wall_W=wall[None])
        refit, times = m.eye_globe.refit, []

        def timed(*args, refit=refit, times=times):
            t0 = time.perf_counter()
            refit(*args)
            times.append(1e6 * (time.perf_counter() - t0))

        m.eye_globe.refit = timed  # each refit of a packet stream, timed where the model calls it
        with collector_paused():
            for i in range(0, len(scan.points), 20):
                m.update(scan.points[i:i + 20], scan.beam_W[i:i + 20])
    print(f"  the eye globe's refit (one of 3 candidates, up to {REFIT_ITERATIONS} steps), pointed eye, packets, "
          f"{len(times)} refits: {summary_us(np.array(times))}")
    t = _update_times(scan.points, PredictiveCriteria(), 1, local=True, beams=scan.beam_W)
    print(f"  AdaptiveEyeModel.update, one A-scan per call, predictive + local, pointed eye: {summary_us(t)}")


def run() -> None:
    eye = make_eye("emmetropic")
    scan = paper_scan(eye, seed=0)
    points, beams = scan.points, scan.beam_W  # the local model is given the beams, as the loop gives them
    _update_times(points, None, 1)  # warm-up: loads the compiled kernels once (a whole spiral: every one it calls)
    _update_times(points, PredictiveCriteria(), 1, RobustFitConfig())  # and those of models.fit.robust_fit
    _update_times(points, PredictiveCriteria(), 1, local=True, beams=beams)  # and those of models.local
    # what a p99 measured here includes: a ~50 us update meets a stall about (rate x 50 us) of the time
    print(f"  this machine, a busy loop: {machine_stalls()}")
    variants = (("paper criteria", None, None, False), ("predictive criteria", PredictiveCriteria(), None, False),
                ("predictive, robust EF", PredictiveCriteria(), RobustFitConfig(), False),
                ("predictive + local", PredictiveCriteria(), None, True))
    for name, criteria, robust, local in variants:
        passes = np.array([_update_times(points, criteria, 1, robust, local, beams=beams if local else None)
                           for _ in range(3)])
        for t in passes:  # as a real-time stream runs it: the cyclic garbage collector paused
            print(f"  AdaptiveEyeModel.update, one A-scan per call, {name:21s}: {summary_us(t)}   mean {t.mean():6.1f} us")
        # the same update in each pass does the same work: its fastest pass is that work
        # without the machine's interruptions (a shared VM's p99 is ~2.7 x its median)
        print(f"    the same, per update the fastest of the 3 passes (work alone):    {summary_us(passes.min(axis=0))}")
    detached = paper_scan(make_eye("detached"), seed=0)  # the local model on the robust globe
    passes = np.array([_update_times(detached.points, PredictiveCriteria(), 1, None, True, beams=detached.beam_W)
                       for _ in range(3)])
    for t in passes:
        print(f"  the same, predictive + local, detached eye:                          {summary_us(t)}")
    print(f"  the same, predictive + local, detached eye, fastest of 3 passes:     {summary_us(passes.min(axis=0))}")
    collector_figures(points)
    t = _update_times(points, None, 10)
    print(f"  AdaptiveEyeModel.update, 10 A-scans per call (200 Hz), per A-scan:       {summary_us(t)}")
    t = _update_times(points, PredictiveCriteria(), 20, local=True, beams=beams)
    print(f"  the same + local model, 20 A-scans per call (the loop's packet), per A-scan: {summary_us(t)}")
    local_field_figures(points)
    small_linalg_figures(points)

    P = Ellipsoid(np.zeros(3), RADII).sample_surface(50, 100, z_max=3.0) + np.random.default_rng(0).normal(0, 0.02, (5000, 3))
    for fit in (fit_ellipsoid, fit_sphere):
        t = time_calls_us(lambda i: fit(P), 50)
        print(f"  {fit.__name__} on 5,000 points: median {np.median(t) / 1e3:.2f} ms")

    e = Ellipsoid(np.zeros(3), RADII)
    Q = np.random.default_rng(1).normal(0, 6, (250_000, 3))
    t0 = time.perf_counter()
    e.signed_distance(Q)
    dt = time.perf_counter() - t0
    print(f"  Ellipsoid.signed_distance (exact, Eberly): {len(Q) / dt / 1e6:.2f} M points/s")
    pointed = make_eye("pointed")
    Qp = np.random.default_rng(2).normal(0, 6, (5000, 3))
    pointed.signed_distance(Qp[:10])  # builds the seed cloud once
    t0 = time.perf_counter()
    pointed.signed_distance(Qp)
    print(f"  pointed eye signed_distance (composite): {len(Qp) / (time.perf_counter() - t0) / 1e3:.1f} k points/s")

    near = e.closest_point(Q[:2000]) + np.random.default_rng(3).uniform(-5, 5, (2000, 1)) * e.gradient(Q[:2000])
    d_drake, us = _drake_signed_distance(near)
    d_exact = e.signed_distance(near)
    err = 1e3 * np.abs(d_drake - d_exact)
    print(f"  Drake ComputeSignedDistanceToPoint on the same ellipsoid, 2,000 points within 5 mm: {us:.1f} us/point")
    for label, sel in (("inside", d_exact > 0), ("outside", d_exact < 0)):
        e_sel = err[sel]
        print(f"    {label:7s} |Drake - exact| median {np.median(e_sel):7.2f} um  p99 {np.percentile(e_sel, 99):8.1f} um  "
              f"max {e_sel.max():8.1f} um  wrong sign {int(np.sum(np.sign(d_drake[sel]) != np.sign(d_exact[sel])))}")
    print(f"  ours on the same points: {1e6 * dt / len(Q):.2f} us/point (vectorised)")
