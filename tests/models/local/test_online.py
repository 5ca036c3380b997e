"""The local model's compiled online step (models.local.online): whether the global quadric
holds the centre is the exact signed distance's answer, and the record of the nodes with
data is every node some point weighed, each once."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Ellipsoid, Sphere
from models.local.config import LocalConfig
from models.local.grid import LocalRetinaModel, sweep_share
from models.local.kernels import global_params
from models.local.online import holds

from test_local_model import cap_points, detachment


def _rotation(angles):
    a, b, c = angles
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(c), -np.sin(c)], [0, np.sin(c), np.cos(c)]])
    return Rz @ Ry @ Rx


@settings(max_examples=300)
@given(radii=st.lists(st.floats(8.0, 16.0), min_size=3, max_size=3),
       angles=st.lists(st.floats(-np.pi, np.pi), min_size=3, max_size=3),
       p=st.lists(st.floats(-16.0, 16.0), min_size=3, max_size=3), margin=st.floats(0.0, 3.0))
def test_holds_is_the_exact_distance_test(radii, angles, p, margin):
    # the ball of the smallest semi-axis decides only what it can; the rest is Eberly's distance
    p = np.array(p)
    for shape in (Ellipsoid(np.array([0.5, -0.3, 0.2]), np.array(radii), _rotation(angles)),
                  Sphere(np.array([0.5, -0.3, 0.2]), radii[0])):
        d = float(shape.signed_distance(p.reshape(1, 3))[0])
        if abs(d - margin) > 1e-9:  # not on the fence, where rounding may go either way
            assert holds(global_params(shape), p, margin) == (d >= margin)


@settings(max_examples=10)
@given(seed=st.integers(0, 10_000), batch=st.integers(1, 60))
def test_every_node_some_point_weighed_is_recorded_once(seed, batch):
    _, P = cap_points(detachment(20.0, 25.0, 2.0), n=1500, seed=seed)
    m = LocalRetinaModel(np.zeros(3))
    for i in range(0, len(P), batch):
        m.update(P[i:i + batch], Sphere(np.zeros(3), 11.0))
    recorded = m._data_nodes[:m._n_data]
    assert len(np.unique(recorded)) == len(recorded)
    assert set(recorded.tolist()) == set(np.flatnonzero(m._wsum > 0.0).tolist())


@settings(max_examples=200)
@given(sizes=st.lists(st.integers(0, 60), min_size=1, max_size=80), rate=st.sampled_from([0.2, 0.25, 0.5, 1.0, 0.1]))
def test_the_sweep_owes_its_rate_per_point_over_any_split(sizes, rate):
    # a stream of single A-scans and one of the loop's packets re-solve as many nodes per point
    credit, total = 0.0, 0
    for n in sizes:
        nodes, credit = sweep_share(credit, rate, n)
        assert nodes >= 0 and 0.0 <= credit < 1.0
        total += nodes
    assert total == int(np.floor(rate * sum(sizes) + 1e-6))


def test_packets_of_twenty_sweep_four_nodes_each_and_single_points_one_in_five():
    credit, per_packet = 0.0, []
    for _ in range(50):
        nodes, credit = sweep_share(credit, LocalConfig().sweep_per_point, 20)
        per_packet.append(nodes)
    assert per_packet == [4] * 50
    credit, singles = 0.0, []
    for _ in range(50):
        nodes, credit = sweep_share(credit, LocalConfig().sweep_per_point, 1)
        singles.append(nodes)
    assert singles == [0, 0, 0, 0, 1] * 10
