"""Where numba keeps the project's compiled code: a folder keyed by the source.

numba's disk cache notices a change in a function's own file, but not in a function it
calls from another file: after an update, a cached caller would run (or fail to load)
with its callee's old code. So the cache lives in a folder named after a digest of every
module of the project's packages: changed code gets a fresh folder and is compiled once
(about a minute and a half), unchanged code loads in seconds. NUMBA_CACHE_DIR, if set,
is used as it is; otherwise VITREOGUARD_CACHE_DIR (default ~/.cache/vitreoguard) holds
the folders; a folder is removed once it is neither among the newest few nor used for a
day (several checkouts or processes may run different sources at once: a folder in use is
never pulled from under them).

Imported first by each of the project's packages, before any compiled function is
declared (numba reads the folder when a function is decorated).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path

import numba

PACKAGES = ("models", "safety", "planning", "eval")
KEEP = 4  # source versions whose compiled code is kept whatever their age
IDLE_S = 86_400.0  # older source versions are removed after a day without use


def cache_root() -> Path:
    """VITREOGUARD_CACHE_DIR, default ~/.cache/vitreoguard."""
    return Path(os.environ.get("VITREOGUARD_CACHE_DIR") or Path.home() / ".cache" / "vitreoguard")


def source_digest() -> str:
    """A digest of every .py file of the project's packages (paths and contents)."""
    h = hashlib.sha256()
    top = Path(__file__).resolve().parent.parent
    for pkg in PACKAGES:
        for path in sorted((top / pkg).rglob("*.py")):
            h.update(str(path.relative_to(top)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


DIGEST = source_digest()


def compiled_dir() -> Path:
    """This source's folder for compiled code (created on first use)."""
    return cache_root() / "compiled" / DIGEST


def _prune(folder: Path) -> None:
    """Remove the source versions' folders beyond the KEEP most recently used that have not
    been used for IDLE_S (best effort)."""
    try:
        now = time.time()
        old = sorted((p for p in folder.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime, reverse=True)[KEEP:]
        for p in old:
            if now - p.stat().st_mtime > IDLE_S:
                shutil.rmtree(p, ignore_errors=True)
    except OSError:
        pass


if not os.environ.get("NUMBA_CACHE_DIR"):
    _dir = compiled_dir()
    try:
        _dir.mkdir(parents=True, exist_ok=True)
        os.utime(_dir)  # most recently used
        _prune(_dir.parent)
        numba.config.CACHE_DIR = str(_dir)
    except OSError:  # an unwritable home: numba's default (beside the sources) still works
        pass
