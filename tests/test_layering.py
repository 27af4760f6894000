"""The package's layering contract (docs/architecture.md), checked as CI checks it.

* ``lint-imports`` (import-linter, contract in ``pyproject.toml``): stages import downwards only,
  ``cli -> evaluation -> applications -> hdr -> derendering -> photometry -> response -> engine | camera | raw
  -> io -> core``. ``.ci/run`` runs it; here a copy of the package with one upward import added
  must make it fail, so the contract cannot pass vacuously.
* No module imports a private name (``_x``) of another module.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "src" / "derender"


def _lint_imports(cwd: Path, pythonpath: Path) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports")
    if exe is None:
        pytest.fail("lint-imports (import-linter) is not installed: pip install -e '.[test]'")
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run([exe, "--no-cache"], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_layering_contract_holds():
    res = _lint_imports(ROOT, ROOT / "src")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "1 kept, 0 broken" in res.stdout


def test_layering_contract_catches_an_upward_import(tmp_path):
    shutil.copytree(PKG, tmp_path / "src" / "derender", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    victim = tmp_path / "src" / "derender" / "io" / "exif.py"
    victim.write_text(victim.read_text() + "\n\ndef _upward():\n    from derender.hdr.registry import merge  # noqa\n")
    res = _lint_imports(tmp_path, tmp_path / "src")
    assert res.returncode != 0
    assert "derender.io is not allowed to import derender.hdr" in res.stdout


def _private_imports(path: Path, root: Path = PKG.parent) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    mod = ".".join(path.relative_to(root).with_suffix("").parts)
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("derender")):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    bad.append(f"{mod}:{node.lineno} imports {alias.name} from {node.module}")
    return bad


def test_no_module_imports_a_private_name_of_another():
    bad = [b for p in sorted(PKG.rglob("*.py")) for b in _private_imports(p)]
    assert not bad, "\n".join(bad)


def test_private_import_check_sees_one(tmp_path):
    p = tmp_path / "derender" / "core" / "probe.py"
    p.parent.mkdir(parents=True)
    p.write_text("from derender.core.memory import _x\nfrom derender.core.memory import __version__\n")
    assert _private_imports(p, tmp_path) == ["derender.core.probe:1 imports _x from derender.core.memory"]
