"""Options travel as typed records in the merge methods and the engine (issue 37): no function of
``derender.hdr`` or ``derender.engine`` takes ``**kwargs`` (a method's options are its record, the
engine's settings :class:`~derender.engine.options.OutputOptions`,
:class:`~derender.engine.options.EngineOptions` and
:class:`~derender.engine.motion.run.MotionOptions`), and none but a compiled kernel takes more
than 8 positional parameters. Read from the source with :mod:`ast`.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "derender"
PACKAGES = ("hdr", "engine")
MAX_POSITIONAL = 8


def _functions(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            yield node


def _compiled(node) -> bool:
    """A numba kernel (``@njit``, ``@numba.jit(...)``...): its arrays come positionally."""
    return any("jit" in ast.unparse(d) for d in getattr(node, "decorator_list", []))


def signature_problems(root: Path = SRC, packages=PACKAGES) -> list[str]:
    """``path:line name: problem`` for every ``**`` parameter and every non-kernel function with
    more than :data:`MAX_POSITIONAL` positional parameters (``self`` counted) under ``packages``."""
    out = []
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            for node in _functions(path):
                name = getattr(node, "name", "<lambda>")
                where = f"{path.relative_to(root)}:{node.lineno} {name}"
                if node.args.kwarg is not None:
                    out.append(f"{where}: **{node.args.kwarg.arg}")
                positional = len(node.args.posonlyargs) + len(node.args.args)
                if positional > MAX_POSITIONAL and not _compiled(node):
                    out.append(f"{where}: {positional} positional parameters")
    return out


def test_no_var_keyword_or_long_positional_parameters_in_hdr_and_engine():
    assert signature_problems() == []


def test_the_signature_check_sees_both(tmp_path):
    pkg = tmp_path / "hdr"
    pkg.mkdir()
    (pkg / "m.py").write_text("def merge(stack, method, **options):\n    pass\n\n"
                              "def wide(a, b, c, d, e, f, g, h, i):\n    pass\n\n"
                              "def narrow(a, b, c, d, e, f, g, h, *, i=0):\n    pass\n\n"
                              "@njit(cache=True)\ndef kernel(a, b, c, d, e, f, g, h, i):\n    pass\n")
    problems = signature_problems(tmp_path, ("hdr",))
    assert problems == ["hdr/m.py:1 merge: **options", "hdr/m.py:4 wide: 9 positional parameters"]
