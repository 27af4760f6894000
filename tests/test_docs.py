"""What the documentation promises that a plain test can check in a second.

The full check is ``sphinx-build -W`` in ``.ci/run`` (every docstring must parse). Two
things it does not catch are checked here: a module constant without a ``#:`` comment
(or docstring) is left out of the API reference without any warning, and a page of
``docs/`` that the package or the README cites must exist.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "derender"


def _module_all(tree: ast.Module) -> list[str]:
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            elts = getattr(node.value, "elts", [])
            return [e.value for e in elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
    return []


def _documented_names(tree: ast.Module, lines: list[str]) -> set[str]:
    """Top-level names with a docstring, a ``#:`` comment (above or on the line) or a
    string right after the assignment (Sphinx's three ways), and imported names."""
    out: set[str] = set()
    body = tree.body
    for i, node in enumerate(body):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            if ast.get_docstring(node):
                out.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            out.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names = [t.id for t in targets if isinstance(t, ast.Name)]
            above = lines[node.lineno - 2].strip() if node.lineno >= 2 else ""
            inline = "#:" in lines[node.lineno - 1]
            after = (i + 1 < len(body) and isinstance(body[i + 1], ast.Expr)
                     and isinstance(getattr(body[i + 1], "value", None), ast.Constant)
                     and isinstance(body[i + 1].value.value, str))
            if above.startswith("#:") or inline or after:
                out.update(names)
    return out


def test_every_public_name_is_documented():
    missing = []
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "__init__.py":  # packages re-export their modules' names
            continue
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text, filename=str(path))
        public = _module_all(tree)
        documented = _documented_names(tree, text.splitlines())
        missing += [f"{path.relative_to(ROOT)}: {name}" for name in public if name not in documented]
    assert not missing, ("public names without a docstring or '#:' comment (the API reference "
                         "would leave them out):\n" + "\n".join(missing))


def test_cited_docs_pages_exist():
    cited: set[str] = set()
    for path in [ROOT / "README.md", *sorted(SRC.rglob("*.py"))]:
        cited.update(re.findall(r"docs/[\w./-]+\.(?:md|rst)", path.read_text(encoding="utf-8")))
    assert cited, "the package cites no documentation page"
    missing = sorted(p for p in cited if not (ROOT / p).is_file())
    assert not missing, f"cited but absent: {missing}"


def test_dotted_names_in_the_docs_resolve():
    """Every ``derender.x.y`` the docs pages and the README name is a module or an attribute of one
    (MyST leaves unresolved cross-references silent, so a moved function would go unnoticed)."""
    import importlib
    import re

    root = Path(__file__).resolve().parents[1]
    texts = [p.read_text() for p in sorted((root / "docs").glob("*.md"))] + [(root / "README.md").read_text()]
    names = sorted({m for t in texts for m in re.findall(r"\bderender(?:\.[A-Za-z_][A-Za-z0-9_]*)+", t)})
    bad = []
    for name in names:
        parts = name.split(".")
        for cut in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            try:
                for attr in parts[cut:]:
                    obj = getattr(obj, attr)
            except AttributeError:
                bad.append(name)
            break
        else:
            bad.append(name)
    assert names and not bad, f"docs name what does not exist: {bad}"
