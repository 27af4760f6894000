"""The public names each package re-exports, read from its ``attach(__name__, {...})`` map.

A stage's ``__init__`` re-exports its modules' names lazily (:mod:`derender.core.lazy`);
the API pages document every name once, in its defining module, and each package page
lists its re-exports with links there. The maps are read from the source with :mod:`ast`
(nothing is imported), so a module added to a map appears in the docs by itself.
"""

from __future__ import annotations

import ast
from pathlib import Path

__all__ = ["package_exports"]


def _attach_map(init: Path) -> dict[str, list[str]] | None:
    """The ``{module: [names]}`` literal passed to ``attach`` in ``init``, or None."""
    tree = ast.parse(init.read_text(encoding="utf-8"), filename=str(init))
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "attach"
                and len(node.args) == 2 and isinstance(node.args[1], ast.Dict)):
            return ast.literal_eval(node.args[1])
    return None


def package_exports(package_dir: Path, package: str = "derender") -> dict[str, list[list[str]]]:
    """``{package: [[name, defining_module], ...]}`` for every package under ``package_dir``.

    The defining module is relative to the package (``"tables"`` for ``derender.engine``),
    as autosummary wants it on the package's own page.
    """
    out: dict[str, list[list[str]]] = {}
    for init in sorted(Path(package_dir).rglob("__init__.py")):
        rel = init.parent.relative_to(package_dir)
        fullname = ".".join((package, *rel.parts))
        mapping = _attach_map(init)
        if mapping:
            out[fullname] = [[name, mod] for mod, names in mapping.items() for name in names]
    return out
