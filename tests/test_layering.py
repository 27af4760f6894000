"""The package's layering contract (docs/architecture.md), checked as CI checks it.

* ``lint-imports`` (import-linter, contracts in ``pyproject.toml``): stages import downwards only,
  ``cli -> evaluation -> applications -> hdr -> derendering -> photometry -> response -> engine | camera | raw
  -> io -> core``, and no two siblings of a package depend on each other in a cycle
  (``acyclic_siblings``: a subpackage counts as one, its modules squashed). ``.ci/run`` runs it;
  here a copy of the package with one upward import added, and one with a cycle inside a stage,
  must make it fail, so the contracts cannot pass vacuously.
* No import cycle between any two modules of the package (the layers contract only sees
  imports between stages): every strongly connected component of grimp's import graph (the
  graph import-linter checks, imports inside functions included) is listed and fails the test.
* No module imports a private name (``_x``) of another module.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
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
    assert "3 kept, 0 broken" in res.stdout


def test_layering_contract_catches_an_upward_import(tmp_path):
    shutil.copytree(PKG, tmp_path / "src" / "derender", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    victim = tmp_path / "src" / "derender" / "io" / "exif.py"
    victim.write_text(victim.read_text() + "\n\ndef _upward():\n    from derender.hdr.registry import merge  # noqa\n")
    res = _lint_imports(tmp_path, tmp_path / "src")
    assert res.returncode != 0
    assert "derender.io is not allowed to import derender.hdr" in res.stdout


def _copy_with_cycle(tmp_path: Path) -> Path:
    """A copy of the package (and pyproject.toml) in which ``engine.frames`` imports
    ``engine.run`` back inside a function (``run`` imports ``frames``): a cycle within one stage."""
    shutil.copytree(PKG, tmp_path / "src" / "derender", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    victim = tmp_path / "src" / "derender" / "engine" / "frames.py"
    victim.write_text(victim.read_text() + "\n\ndef _back():\n    from derender.engine.run import run  # noqa\n")
    return tmp_path


def test_layering_contract_catches_a_cycle_inside_a_stage(tmp_path):
    root = _copy_with_cycle(tmp_path)
    res = _lint_imports(root, root / "src")
    assert res.returncode != 0
    assert "No cycles are allowed in derender.engine" in res.stdout


#: Lists the strongly connected components (size > 1, or a module importing itself) of the
#: package's import graph, as ``a -> b`` lines per component, in a fresh interpreter so that
#: the package analysed is the one under ``PYTHONPATH``.
_CYCLES = """
import sys
import grimp

g = grimp.build_graph("derender", cache_dir=None)
adj = {m: sorted(g.find_modules_directly_imported_by(m)) for m in sorted(g.modules)}
index, low, stack, on, comps = {}, {}, [], set(), []

def visit(v):
    index[v] = low[v] = len(index)
    stack.append(v)
    on.add(v)
    for w in adj[v]:
        if w not in index:
            visit(w)
            low[v] = min(low[v], low[w])
        elif w in on:
            low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        comp = []
        while not comp or comp[-1] != v:
            comp.append(stack.pop())
            on.discard(comp[-1])
        if len(comp) > 1 or v in adj[v]:
            comps.append(sorted(comp))

sys.setrecursionlimit(10000)
for m in adj:
    if m not in index:
        visit(m)
print(len(g.modules))
for comp in sorted(comps):
    print("cycle: " + ", ".join(comp))
    print("".join(f"  {a} -> {b}\\n" for a in comp for b in adj[a] if b in comp), end="")
"""


def _import_cycles(src: Path) -> tuple[int, list[str]]:
    env = {**os.environ, "PYTHONPATH": str(src)}
    res = subprocess.run([sys.executable, "-c", _CYCLES], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    lines = res.stdout.splitlines()
    return int(lines[0]), lines[1:]


def test_no_import_cycles_between_modules():
    n_modules, cycles = _import_cycles(ROOT / "src")
    assert n_modules > 100          # the whole package was read
    assert not cycles, "import cycles (break each with a leaf module or by moving the caller):\n" + "\n".join(cycles)


def test_import_cycle_check_sees_one(tmp_path):
    root = _copy_with_cycle(tmp_path)
    _, cycles = _import_cycles(root / "src")
    assert "cycle: derender.engine.frames, derender.engine.run" in cycles
    assert "  derender.engine.frames -> derender.engine.run" in cycles


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
