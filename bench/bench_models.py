"""Eye model figures: per-A-scan model update, batch fits, signed-distance
throughput, and Drake's ComputeSignedDistanceToPoint (the design's peer) on the same
ellipsoid: accuracy against our exact distance and time per point."""
from __future__ import annotations

import time

import numpy as np

from bench.timing import summary_us, time_calls_us
from models import AdaptiveEyeModel, Ellipsoid, fit_ellipsoid, fit_sphere
from models.eyes import make_eye
from models.scan.paper_scan import paper_scan

MM_PER_M = 1e3


def _per_point_rate(fn, Q: np.ndarray) -> float:
    """Points per second of fn(Q) (one vectorised call, after a warm-up on a few points)."""
    fn(Q[:8])
    t0 = time.perf_counter()
    fn(Q)
    return len(Q) / (time.perf_counter() - t0)


def _rays_to_the_posterior_wall(eye, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n unit rays (origins, directions; (n, 3) each, W = E) from inside the eye, 0-25 mm
    short of their hit on the posterior wall: the sensor's case in the closed loop."""
    U = rng.normal(size=(n, 3))
    U[:, 2] = -np.abs(U[:, 2]) - 0.8
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    D = U + 0.3 * rng.normal(size=(n, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    s = rng.uniform(0.0, 25.0, n)
    P = eye.surface_points(U)
    for _ in range(50):  # shorten until every origin lies inside
        inside = eye.signed_distance(P - s[:, None] * D) > 0
        if inside.all():
            break
        s = np.where(inside, s, 0.7 * s)
    return P - s[:, None] * D, D


def drake_signed_distance(radii_mm: np.ndarray, Q_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Drake's signed distance (mm, converted to our convention: > 0 inside) from points Q_mm
    (M, 3) mm to an anchored Ellipsoid of semi-axes radii_mm at the world origin, and the
    time per point (us). Drake works in metres and its distance is < 0 inside."""
    from pydrake.geometry import Ellipsoid as DrakeEllipsoid
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, CoulombFriction
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.0)
    a, b, c = (float(r) / MM_PER_M for r in radii_mm)
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(), DrakeEllipsoid(a, b, c), "retina",
                                    CoulombFriction(1.0, 1.0))
    plant.Finalize()
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    p_WQ_m = Q_mm / MM_PER_M
    threshold_m = 1.0  # far beyond any query: every point gets an answer
    out = np.empty(len(Q_mm))
    t0 = time.perf_counter()
    for i, p in enumerate(p_WQ_m):
        (result,) = query.ComputeSignedDistanceToPoint(p, threshold_m)
        out[i] = -result.distance * MM_PER_M
    return out, 1e6 * (time.perf_counter() - t0) / len(Q_mm)


def run() -> None:
    eye = make_eye("emmetropic")
    points = paper_scan(eye, noise_um=20.0, seed=0).points
    model = AdaptiveEyeModel()
    t = time_calls_us(lambda i: model.update(points[i]), len(points))
    print(f"  AdaptiveEyeModel.update per A-scan, paper spiral, emmetropic ({len(points)} A-scans, "
          f"switched at {model.transition_index}): {summary_us(t)}")

    rng = np.random.default_rng(0)
    truth = Ellipsoid(np.zeros(3), eye.radii)
    P = truth.sample_surface(50, 100, z_max=truth.radii[2] - 5.0) + rng.normal(0.0, 0.02, (5000, 3))
    for fit in (fit_ellipsoid, fit_sphere):
        t = time_calls_us(lambda i: fit(P), 30)
        print(f"  {fit.__name__} on 5,000 points: median {np.median(t) / 1e3:.2f} ms, max {t.max() / 1e3:.2f} ms")

    Q = rng.uniform(-1.5, 1.5, (250_000, 3)) * eye.radii
    rate = _per_point_rate(truth.signed_distance, Q)
    print(f"  Ellipsoid.signed_distance (exact, Eberly), 250,000 points: {rate / 1e6:.2f} M points/s "
          f"({1e6 / rate:.2f} us/point)")
    for name in ("pointed", "staphyloma", "detached"):
        composite = make_eye(name)
        O, D = _rays_to_the_posterior_wall(composite, 1000, rng)
        ray_us = time_calls_us(lambda i: composite.ray_cast(O[10 * i:10 * i + 10], D[10 * i:10 * i + 10]), 100)
        sd10_us = time_calls_us(lambda i: composite.signed_distance(Q[10 * i:10 * i + 10]), 100)
        rate = _per_point_rate(composite.signed_distance, Q[:5000])
        print(f"  {name} eye (composite): ray_cast per 10 rays from inside {summary_us(ray_us)}; "
              f"signed_distance 10 points median {np.median(sd10_us):.0f} us, 5,000 points {5000 / rate * 1e3:.0f} ms")

    # Points within 5 mm of the retina, inside and outside, along the surface normals.
    X = truth.sample_surface(40, 50)
    near = X + rng.uniform(-5.0, 5.0, (len(X), 1)) * truth.gradient(X)
    ours = truth.signed_distance(near)
    t0 = time.perf_counter()
    truth.signed_distance(near)
    ours_us = 1e6 * (time.perf_counter() - t0) / len(near)
    drake, drake_us = drake_signed_distance(eye.radii, near)
    err_um = 1e3 * np.abs(drake - ours)
    print(f"  Drake QueryObject.ComputeSignedDistanceToPoint on an Ellipsoid of semi-axes {eye.radii.tolist()} mm, "
          f"{len(near)} points within 5 mm: {drake_us:.1f} us/point (ours {ours_us:.2f} us/point vectorised)")
    for label, sel in (("inside", ours > 0), ("outside", ours < 0)):
        e = err_um[sel]
        wrong = int(np.sum(np.sign(drake[sel]) != np.sign(ours[sel])))
        print(f"    {label:7s} |Drake - exact|: median {np.median(e):8.2f} um  p99 {np.percentile(e, 99):8.2f} um  "
              f"max {e.max():8.2f} um  sign disagreements {wrong}")
