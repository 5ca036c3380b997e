"""The local model's choice (models.local.selection) on the paper's spiral: taken up on a
pathology, and kept to the end of the spiral."""
import numpy as np
import pytest

from models import AdaptiveEyeModel
from models.adaptive.outlier_gate import OutlierGate
from models.adaptive.transition import PredictiveCriteria
from models.eyes import make_eye
from models.local.grid import LocalRetinaModel
from models.scan.paper_scan import paper_scan


def level_at_the_end(shape: str, seed: int) -> str:
    eye = make_eye(shape)
    model = AdaptiveEyeModel(PredictiveCriteria(), OutlierGate(), None, LocalRetinaModel(eye.pose.p_WE))
    for p in paper_scan(eye, seed=seed).points:
        model.update(p)
    return model.level


@pytest.mark.parametrize("shape", ["detached", "staphyloma"])
def test_a_pathology_ends_on_the_local_model(shape):
    """Past the detachment or the pouch the spiral ends on healthy periphery, which both
    models predict alike: the correction must outlast it (given up there, the filter is
    left the robust globe, millimetres off over the pathology)."""
    assert level_at_the_end(shape, 0) == "local"
