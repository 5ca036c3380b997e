"""The model's update stream with the cyclic garbage collector paused (models.realtime):
it leaks nothing, because the update makes no reference cycles."""
from __future__ import annotations

import gc

import numpy as np
import pytest

from models import AdaptiveEyeModel, PredictiveCriteria
from models.eyes import make_eye
from models.fit.robust_fit import RobustFitConfig
from models.local.grid import LocalRetinaModel
from models.realtime import collector_paused
from models.scan.paper_scan import paper_scan


def _garbage_after(stream) -> int:
    """Cyclic garbage left by stream() run with the collector paused: what gc.collect()
    finds unreachable afterwards (0: reference counting freed everything)."""
    gc.collect()
    with collector_paused():
        stream()
        found = gc.collect()
    return found


@pytest.mark.parametrize("shape, robust, packet", [("emmetropic", None, 1), ("detached", RobustFitConfig(), 20)])
def test_the_update_leaves_no_cyclic_garbage_over_a_whole_spiral(shape, robust, packet):
    eye = make_eye(shape)
    P = paper_scan(eye, noise_um=20.0, seed=0).points
    P[5::89] += 3.0 * eye.gradient(P[5::89])  # floaters: the gate rejects them
    P[::97] = np.nan  # bad samples are skipped and counted
    new_model = lambda: AdaptiveEyeModel(PredictiveCriteria(), robust=robust, local=LocalRetinaModel(eye.pose.p_WE))  # noqa: E731

    def stream():
        for i in range(0, len(P), packet):
            model.update(P[i:i + packet])

    model = new_model()
    stream()  # numba's first call of a compiled function makes a few cycles of its own (ctypes types): once
    model = new_model()
    assert _garbage_after(stream) == 0
    # the stream went through every phase: the ellipsoid (or the robust globe) under the
    # local part, the local part in use, points rejected
    assert model.global_for_local() is not model.sphere
    assert model.level == "local" or model.kind == "ellipsoid"
    assert model.n_rejected_nonfinite > 0 and model.n_rejected_outliers > 0


def test_a_cycle_made_in_the_block_is_found_after_it():
    def stream():
        a = []
        a.append(a)

    assert _garbage_after(stream) >= 1


@pytest.mark.parametrize("enabled", [True, False])
def test_the_collector_state_is_restored_also_after_an_error(enabled):
    (gc.enable if enabled else gc.disable)()
    try:
        with pytest.raises(RuntimeError):
            with collector_paused():
                assert not gc.isenabled()
                with collector_paused():
                    pass
                assert not gc.isenabled()
                raise RuntimeError("stop")
        assert gc.isenabled() == enabled
    finally:
        gc.enable()
