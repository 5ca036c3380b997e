"""The closed loop compiles (or loads from numba's cache) the kernels its runs use while it
is constructed, inside the command line's compile phase with its progress line: a kernel
first called during a run compiles there instead, ~9 s of a first run's scan with no
progress (the local field in the model's own form, which the build's probes read)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

PROBE = """
import json
from eval.closed_loop import ClosedLoop, LoopConfig
from planning import SurgeryScenario
from models.local.field_kernels import local_model_field
ClosedLoop(SurgeryScenario(), LoopConfig())
print(json.dumps({"local_model_field": len(local_model_field.signatures)}))
"""


@pytest.mark.slow
def test_constructing_the_loop_compiles_the_local_fields_own_form():
    """In a fresh process (nothing compiled or loaded yet): after the loop's construction
    the model's own form of the local field, which Python calls, has a compiled (or
    cache-loaded) signature. (The filter's barrier form is compiled into the filter's step,
    whose cached code does not go through that kernel's dispatcher.)"""
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=600, check=True)
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert counts["local_model_field"] >= 1, counts
