"""The distance extractor's outputs on a fixed corpus of synthetic A-scans.

The corpus (random distances, incidence angles, gains, floaters, and damaged scans of
every kind) is drawn from a seed; the expected Measurements are stored in
tests/data/iioct_segmentation_corpus.npz. Any change to the extractor's signal
processing must leave every Measurement as it is: validity and reason exactly, the
floats to 1e-12 (the synthesis goes through BLAS, whose last bits may differ between
machines). When the outputs change on purpose, rewrite the file with
`python -m tests.models.iioct.test_segmentation_corpus` and say why in the commit.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.iioct import REASONS, DistanceExtractor, Floater, OctEngine, synthesize_ascan

ENGINE = OctEngine()
SEED, N_SCANS = 20240611, 4000
EXPECTED = Path(__file__).resolve().parents[2] / "data" / "iioct_segmentation_corpus.npz"
# extractor options per stored set: the defaults, and a low threshold with a narrow
# merge gap and more candidates (many clusters, noise spikes among them)
CONFIGS = {"default": {}, "sensitive": {"min_peak_snr_db": 10.0, "merge_gap_mm": 0.05, "max_candidates": 5}}
_KEYS = ("distance_mm", "valid", "confidence", "reason", "snr_db")


def _damage(x: np.ndarray, kind: int, rng: np.random.Generator):
    """The scan x damaged in one of the ways a sensor or its driver can fail (kind 0..9)."""
    n = len(x)
    if kind == 0:  # a NaN or infinite sample
        x[rng.integers(n)] = (np.nan, np.inf, -np.inf)[rng.integers(3)]
    elif kind == 1:  # a negative sample
        x[rng.integers(n)] = -rng.uniform(0.0, 10.0) - 1e-9
    elif kind == 2:  # dropped or extra samples
        return x[:n - rng.integers(1, 5)] if rng.random() < 0.5 else np.append(x, x[:rng.integers(1, 5)])
    elif kind == 3:  # blank or clipped
        return np.zeros(n) if rng.random() < 0.5 else np.full(n, ENGINE.full_scale)
    elif kind == 4:  # noise only
        return np.sqrt(rng.standard_exponential(n)) * rng.uniform(0.5, 3.0)
    elif kind == 5:  # tip reflection lost (the fibre's end face)
        k = int(2.0 * ENGINE.tip_offset_mm / ENGINE.sample_spacing_mm)
        x[:k] = np.sqrt(rng.standard_exponential(k))
    elif kind == 6:  # gain error: every sample scaled (may clip)
        x = np.minimum(x * 10.0 ** rng.uniform(-1.5, 1.0), ENGINE.full_scale)
    elif kind == 7:  # raised noise floor
        x = x + rng.uniform(0.5, 20.0)
    elif kind == 8:  # a burst of strong interference somewhere
        a = int(rng.integers(0, n - 40))
        x[a:a + 40] += rng.uniform(5.0, 300.0) * rng.random(40)
        np.minimum(x, ENGINE.full_scale, out=x)
    elif kind == 9:  # not numbers at all
        return ["x"] * n if rng.random() < 0.5 else None
    return x


def corpus(seed: int = SEED, n: int = N_SCANS) -> list:
    """n A-scans drawn from `seed`: retinae at 0.05 mm to beyond the imaging depth and
    0-75 deg incidence, 0-3 floaters, a gain offset in one scan of six, and one scan in
    eight damaged (see _damage)."""
    rng = np.random.default_rng(seed)
    far = ENGINE.max_distance_mm
    scans = []
    for _ in range(n):
        d = rng.uniform(0.05, 26.0) if rng.random() < 0.9 else rng.uniform(26.0, far + 3.0)
        th = rng.uniform(0.0, np.deg2rad(75.0))
        floaters = [Floater(rng.uniform(0.05, d + 1.0), snr_db=rng.uniform(10.0, 50.0),
                            thickness_um=rng.uniform(2.0, 30.0)) for _ in range(rng.integers(0, 4))]
        gain = rng.uniform(-25.0, 20.0) if rng.random() < 1.0 / 6.0 else 0.0
        x = synthesize_ascan(d, th, rng, engine=ENGINE, floaters=floaters, gain_db=gain)
        scans.append(_damage(x, int(rng.integers(10)), rng) if rng.random() < 0.125 else x)
    return scans


def measure(scans: list, options: dict) -> dict[str, np.ndarray]:
    """The extractor's Measurements over `scans` as arrays (reason: index in REASONS, -1 if valid)."""
    ex = DistanceExtractor(ENGINE, **options)
    out = [ex(x) for x in scans]
    return {"distance_mm": np.array([m.distance_mm for m in out]), "valid": np.array([m.valid for m in out]),
            "confidence": np.array([m.confidence for m in out]),
            "reason": np.array([REASONS.index(m.reason) if m.reason else -1 for m in out], dtype=np.int8),
            "snr_db": np.array([m.snr_db for m in out])}


@pytest.fixture(scope="module")
def scans():
    return corpus()


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_every_measurement_equals_the_stored_one(scans, config):
    got = measure(scans, CONFIGS[config])
    with np.load(EXPECTED) as f:
        want = {k: f[f"{config}/{k}"] for k in _KEYS}
    np.testing.assert_array_equal(got["valid"], want["valid"])
    np.testing.assert_array_equal(got["reason"], want["reason"])
    for k in ("distance_mm", "confidence", "snr_db"):
        np.testing.assert_allclose(got[k], want[k], rtol=0.0, atol=1e-12, err_msg=k)


def test_the_corpus_covers_every_outcome(scans):
    """Each reason (and a valid majority) occurs, so the comparison exercises every path."""
    with np.load(EXPECTED) as f:
        reasons = np.concatenate([f[f"{c}/reason"] for c in CONFIGS])
        valid = f["default/valid"]
    assert set(np.unique(reasons).tolist()) == set(range(-1, len(REASONS)))
    assert valid.mean() > 0.4 and len(scans) == len(valid) == N_SCANS


if __name__ == "__main__":
    xs = corpus()
    np.savez_compressed(EXPECTED, **{f"{c}/{k}": v for c, o in CONFIGS.items() for k, v in measure(xs, o).items()})
    print(f"wrote {EXPECTED}")


def test_no_decision_rides_on_the_last_bits(scans):
    """Each scan scaled by 1 + 1e-13 (far below the 20 um noise, at the level of a
    machine's different rounding) gets the same validity and reason: a decision left to
    rounding (two clusters finding the same match) would differ between machines."""
    nudged = [x * (1.0 + 1e-13) if isinstance(x, np.ndarray) else x for x in scans]
    for options in CONFIGS.values():
        a, b = measure(scans, options), measure(nudged, options)
        np.testing.assert_array_equal(a["valid"], b["valid"])
        np.testing.assert_array_equal(a["reason"], b["reason"])
