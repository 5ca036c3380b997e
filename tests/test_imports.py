"""Guards on the packages' boundaries and sizes.

- No module imports another top-level package's private name: a name, or a component of
  the module path, that starts with "_" (dunders aside), imported from a different
  package among models/, safety/, planning/, eval/ (e.g. `from models._validation
  import as_points` in eval/, or `from planning.ik import _signed_angle`).
- No module under those packages is longer than MAX_LINES.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("models", "safety", "planning", "eval")
MAX_LINES = 400


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def modules() -> list[Path]:
    """The .py files of the four packages."""
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def private_imports(path: Path) -> list[str]:
    """'file:line: statement' for each import in `path` of another package's private name."""
    own = path.relative_to(ROOT).parts[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [(alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            targets = [(node.module, alias.name) for alias in node.names]
        else:
            continue  # relative imports stay inside their own package
        for module, name in targets:
            parts = module.split(".")
            if parts[0] not in PACKAGES or parts[0] == own:
                continue
            if any(_private(p) for p in parts[1:]) or (name is not None and _private(name)):
                what = module if name is None else f"{module} import {name}"
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {what}")
    return found


def long_modules(paths) -> list[str]:
    return [f"{p.relative_to(ROOT)}: {n} lines" for p in paths if (n := len(p.read_text().splitlines())) > MAX_LINES]


def test_the_guard_finds_private_names_and_private_module_paths(tmp_path, monkeypatch):
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    (tmp_path / "eval").mkdir()
    f = tmp_path / "eval" / "x.py"
    f.write_text("import models._kernels\nfrom planning.ik import _signed_angle, rcm_ik\nfrom models import Sphere\n"
                 "from eval._own import y\nfrom . import _local\nfrom safety import __version__\nimport numpy._core\n")
    assert private_imports(f) == ["eval/x.py:1: models._kernels", "eval/x.py:2: planning.ik import _signed_angle"]


def test_no_module_imports_a_private_name_of_another_package():
    assert [line for p in modules() for line in private_imports(p)] == []


def test_no_module_is_longer_than_400_lines():
    assert long_modules(modules()) == []
