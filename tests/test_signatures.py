"""Options travel as typed records in the merge methods and the engine (issue 37): no function of
``derender.hdr`` or ``derender.engine`` takes ``**kwargs`` (a method's options are its record, the
engine's settings :class:`~derender.engine.options.OutputOptions`,
:class:`~derender.engine.options.EngineOptions` and
:class:`~derender.engine.motion.run.MotionOptions`). Read from the source with :mod:`ast`. (The
limit of 8 positional parameters, for the whole package, is tests/test_shape.py's.)
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "derender"
PACKAGES = ("hdr", "engine")


def _functions(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            yield node


def signature_problems(root: Path = SRC, packages=PACKAGES) -> list[str]:
    """``path:line name: **name`` for every ``**`` parameter of a function under ``packages``."""
    out = []
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            for node in _functions(path):
                name = getattr(node, "name", "<lambda>")
                where = f"{path.relative_to(root)}:{node.lineno} {name}"
                if node.args.kwarg is not None:
                    out.append(f"{where}: **{node.args.kwarg.arg}")
    return out


def test_no_var_keyword_parameters_in_hdr_and_engine():
    assert signature_problems() == []


def test_the_signature_check_sees_var_keywords(tmp_path):
    pkg = tmp_path / "hdr"
    pkg.mkdir()
    (pkg / "m.py").write_text("def merge(stack, method, **options):\n    pass\n\n"
                              "def typed(stack, method, options=None, *, motion=None):\n    pass\n")
    assert signature_problems(tmp_path, ("hdr",)) == ["hdr/m.py:1 merge: **options"]
