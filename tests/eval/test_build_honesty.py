"""The local model's sigma on the way through a build (eval.experiments.model_report.BuildHonesty)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from eval.experiments.model_report import BuildHonesty
from models import Sphere


class _Eye:
    """A 12 mm spherical retina about the origin: its reference samples on a z-band."""

    def reference_samples(self, n_theta, n_phi):
        z = np.linspace(-11.0, 11.0, n_theta)
        phi = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
        Z, PHI = np.meshgrid(z, phi, indexing="ij")
        rho = np.sqrt(144.0 - Z ** 2)
        return np.column_stack([(rho * np.cos(PHI)).ravel(), (rho * np.sin(PHI)).ravel(), Z.ravel()])


class _Field:
    """A sphere model of radius `radius_mm` about the origin with a constant sigma."""

    def __init__(self, radius_mm, sigma_mm):
        self.sphere, self.sigma_mm = Sphere(np.zeros(3), radius_mm), sigma_mm

    def signed_distance(self, Q):
        return self.sphere.signed_distance(Q)

    def uncertainty(self, Q):
        return np.full(len(Q), self.sigma_mm)


def _snap(t_s, field):
    return SimpleNamespace(t_s=t_s, field=field)


def test_the_worst_probe_is_reported_and_probes_are_spaced_in_simulated_time():
    watch = BuildHonesty(_Eye(), every_s=0.25, n_grid=20)
    watch(_snap(0.0, None))  # the prior: no field, not measured
    watch(_snap(0.1, _Field(11.0, 0.5)))  # 1 mm inside the retina, 3 sigma 1.5 mm: covered
    watch(_snap(0.2, _Field(13.0, 0.1)))  # within 0.25 s of the last probe: skipped
    watch(_snap(0.4, _Field(12.5, 0.1)))  # 0.5 mm beyond the retina, 3 sigma 0.3 mm: every sample unsafe by 0.2 mm
    watch(_snap(0.7, _Field(11.5, 0.1)))  # 0.5 mm inside, not covered: safe-side misses
    s = watch.summary()
    assert s["probes"] == 3
    assert s["lowest_sigma3_coverage"] == 0.0 and s["lowest_at_s"] == 0.4  # the first of the uncovered probes
    assert s["largest_unsafe_fraction"] == 1.0 and s["largest_unsafe_at_s"] == 0.4
    assert s["worst_excess_um"] == pytest.approx(200.0, abs=1e-6)


def test_no_field_no_summary_and_no_unsafe_side_no_time():
    watch = BuildHonesty(_Eye(), n_grid=10)
    watch(_snap(0.0, None))
    assert watch.summary() is None
    watch(_snap(1.0, _Field(11.9, 0.1)))  # 0.1 mm inside: covered
    s = watch.summary()
    assert (s["lowest_sigma3_coverage"], s["largest_unsafe_fraction"], s["largest_unsafe_at_s"]) == (1.0, 0.0, None)
    assert s["worst_excess_um"] == pytest.approx(-400.0, abs=1e-6)  # -0.1 - 0.3 mm
