"""The compiled-code folders: a folder another checkout or process may still use is never
removed; an old, idle one is."""
from __future__ import annotations

import os
import time

from models import compiled_cache


def test_prune_keeps_the_newest_and_every_recently_used_folder(tmp_path):
    now = time.time()
    ages_s = {"new0": 0, "new1": 10, "new2": 20, "new3": 30, "busy": 3600, "idle": 2 * compiled_cache.IDLE_S}
    for name, age in ages_s.items():
        (tmp_path / name).mkdir()
        os.utime(tmp_path / name, (now - age, now - age))
    compiled_cache._prune(tmp_path)
    # beyond the KEEP newest, only the one idle for longer than IDLE_S goes
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(set(ages_s) - {"idle"})
