"""Functions that fit on a screen (issue 37, item 5), checked on the package's source with ``ast``.

* No function or method in ``src/derender`` is longer than :data:`MAX_LINES` lines. A function's
  length is counted from its first statement after the docstring to its last line: the
  signature, the decorators and the docstring do not count; nested functions count in the
  function that holds them (and on their own).
* None takes more than :data:`MAX_POSITIONAL` positional parameters (``self`` / ``cls`` not
  counted; keyword-only parameters, after ``*``, are free: they are named at every call).

Exceptions, by decorator: numba kernels (``@njit``, ``@jit``, ``@vectorize``, ``@guvectorize``,
``@stencil``, ``@cfunc``: a compiled loop is read as one piece, and its arguments are the arrays
it works on), and typer commands (``@app.command``, ``@app.callback``: every option of a command
is a parameter, and its body is the command's declaration).

:data:`LONG_ALLOWED` and :data:`POSITIONAL_ALLOWED` list offenders in files other helpers were
rewriting in the same round of issue 37 (their fixes land separately); the lead empties both lists
once those branches are merged. An entry that no longer offends fails the test too, so the
lists only shrink.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "src" / "derender"

#: Longest function body allowed, in lines (docstring, signature and decorators not counted).
MAX_LINES = 80
#: Most positional parameters allowed (``self`` / ``cls`` not counted).
MAX_POSITIONAL = 8

#: Decorator names that mark a numba kernel (the name itself, or ``numba.<name>``).
NUMBA_DECORATORS = frozenset({"njit", "jit", "vectorize", "guvectorize", "stencil", "cfunc", "generated_jit"})
#: Decorator attributes that mark a typer command (``@app.command(...)``, ``@app.callback(...)``).
TYPER_DECORATORS = frozenset({"command", "callback"})

#: Too long, in files being rewritten on other branches of issue 37 (path under src/derender,
#: qualified name) -> who is fixing it. Emptied by the lead after the merge.
LONG_ALLOWED: dict[tuple[str, str], str] = {}
#: Too many positional parameters, same rule as :data:`LONG_ALLOWED`.
POSITIONAL_ALLOWED: dict[tuple[str, str], str] = {}


def _decorator_name(node: ast.expr) -> str:
    """The last name of a decorator: ``njit`` for ``@njit``, ``@njit(...)``, ``@numba.njit(...)``;
    ``command`` for ``@app.command(...)``."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Name):
        return node.id
    return ""


def body_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement after the docstring to the function's last line."""
    body = fn.body
    first = body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        if len(body) == 1:
            return 0
        first = body[1]
    return fn.end_lineno - first.lineno + 1


def positional_count(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Positional parameters (positional-only and positional-or-keyword), ``self`` / ``cls`` not counted."""
    params = [*fn.args.posonlyargs, *fn.args.args]
    if params and params[0].arg in ("self", "cls"):
        params = params[1:]
    return len(params)


def offenders(source: str, rel: str) -> tuple[list[tuple[str, str, int]], list[tuple[str, str, int]]]:
    """``(too long, too many positional)`` in one module's ``source``: ``(rel, qualified name, count)``
    each, numba kernels and typer commands left out."""
    long, positional = [], []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}{child.name}"
                decorators = {_decorator_name(d) for d in child.decorator_list}
                if not decorators & (NUMBA_DECORATORS | TYPER_DECORATORS):
                    if (n := body_lines(child)) > MAX_LINES:
                        long.append((rel, name, n))
                    if (p := positional_count(child)) > MAX_POSITIONAL:
                        positional.append((rel, name, p))
                visit(child, f"{name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return long, positional


def _package_offenders() -> tuple[list[tuple[str, str, int]], list[tuple[str, str, int]]]:
    long, positional = [], []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).as_posix()
        lo, po = offenders(path.read_text(encoding="utf-8"), rel)
        long += lo
        positional += po
    return long, positional


def _report(found: list[tuple[str, str, int]], allowed: dict, what: str) -> list[str]:
    lines = [f"  src/derender/{rel}: {name} ({n} {what})" for rel, name, n in found if (rel, name) not in allowed]
    keys = {(rel, name) for rel, name, _ in found}
    lines += [f"  src/derender/{rel}: {name} is allowed ({why}) but no longer offends: remove it from the list"
              for (rel, name), why in allowed.items() if (rel, name) not in keys]
    return lines


def test_no_function_is_over_80_lines():
    long, _ = _package_offenders()
    problems = _report(long, LONG_ALLOWED, f"lines > {MAX_LINES}, docstring excluded")
    assert not problems, ("functions too long to read on one screen (split them into pieces named for what "
                          "they do):\n" + "\n".join(problems))


def test_no_function_takes_more_than_8_positional_parameters():
    _, positional = _package_offenders()
    problems = _report(positional, POSITIONAL_ALLOWED, f"positional parameters > {MAX_POSITIONAL}")
    assert not problems, ("functions with too many positional parameters (make the rest keyword-only, "
                          "or pass a small record):\n" + "\n".join(problems))


def test_the_check_sees_long_functions_and_long_signatures_but_not_kernels_or_commands():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))       # exactly MAX_LINES lines: allowed
    nested = textwrap.indent(body, "        ")
    source = f'''
import numba, typer
app = typer.Typer()

def fits(a, b):
    """A docstring
    of several lines does not count."""
{body}

def too_long():
{body}
    return x0

class Holder:
    def method(self, a, b, c, d, e, f, g, h):
        return a

    def crowded(self, a, b, c, d, e, f, g, h, i):
        def inner():
{nested}
            return 1
        return inner

def keywords(a, b, c, d, e, f, g, h, *, i, j, k):
    return a

@numba.njit(cache=True)
def kernel(a, b, c, d, e, f, g, h, i):
{body}
    return a

@app.command("merge")
def merge_cmd(a, b, c, d, e, f, g, h, i, j):
{body}
    return a
'''
    long, positional = offenders(source, "x.py")
    assert [(name, n) for _, name, n in long] == [("too_long", MAX_LINES + 1), ("Holder.crowded", MAX_LINES + 3),
                                                  ("Holder.crowded.inner", MAX_LINES + 1)]
    assert [(name, n) for _, name, n in positional] == [("Holder.crowded", 9)]
