"""Output handling for the command line: validated output folders and all-or-nothing writes."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


class UsageError(Exception):
    """Bad command-line input: the CLI prints the message and exits with code 2."""


def _probe(folder: Path) -> None:
    """Create and remove a file in `folder`: the test both output checks make (os.access
    may call a read-only mount writable); OSError if it cannot."""
    with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
        pass


def check_out_dir(path) -> Path:
    """Check, leaving nothing behind, that `path` can be an output folder: a folder
    already, or to be made inside the nearest existing folder above it; a probe file is
    made and removed there, as prepare_out_dir makes it (for a command with two output
    folders: both checked before either is made). UsageError if not."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UsageError(f"output directory {out} is not writable: it is a file")
    above = out
    while not above.exists():
        above = above.parent
    if not above.is_dir():
        raise UsageError(f"output directory {out} is not writable: {above} is not a folder")
    try:
        _probe(above)
    except OSError as exc:
        raise UsageError(f"output directory {out} is not writable: {above}: {exc.strerror or exc}") from None
    return out


def prepare_out_dir(path) -> Path:
    """Create `path` if needed and check that it is writable (a probe file made and
    removed); raise UsageError if not."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        _probe(out)
    except OSError as exc:
        raise UsageError(f"output directory {out} is not writable: {exc.strerror or exc}") from None
    return out


def write_atomic(path, data: bytes | str) -> Path:
    """Write `data` to `path` through a temporary file and a rename: readers never see half a file."""
    path = Path(path)
    raw = data.encode() if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; results are for everyone to read
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json(path, obj) -> Path:
    """Write `obj` as indented JSON (NaN is refused: use None for 'no value')."""
    return write_atomic(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def save_figure(fig, path, tight_bbox: bool = True) -> Path:
    """Save a matplotlib figure as PNG atomically and close it; `tight_bbox` False for a
    figure laid out already (tight_layout): one rendering instead of two."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight" if tight_bbox else None)
    plt.close(fig)
    return write_atomic(path, buf.getvalue())
