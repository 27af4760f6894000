"""Sphinx configuration of derender's documentation.

Build (fails on any warning, as ``.ci/run`` does)::

    pip install -e '.[docs]'
    sphinx-build -W --keep-going -b html docs docs/_build/html

At build time this file draws the figures with matplotlib (``docs/figures.py`` into
``docs/_generated/``), generates the API pages from the docstrings (autosummary, one page
per defining module) and the CLI reference from the typer app (``docs/_ext/typer_cli.py``).
"""

from __future__ import annotations

import inspect
import os
import shutil
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT / "src"))  # the checked-out sources, whether or not installed
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(DOCS))
os.environ.setdefault("MPLBACKEND", "Agg")

import figures  # noqa: E402
from api_exports import package_exports  # noqa: E402

import derender  # noqa: E402

project = "derender"
author = "the derender authors"
copyright = "the derender authors, BSD-3-Clause"
release = derender.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "typer_cli",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_generated", "_templates", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]
html_static_path: list[str] = []   # no static files of our own (figures are generated into _generated)
html_theme = "furo"
html_title = f"derender {release}"

smartquotes = False  # option names (--times) and quotes stay as typed
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

# API reference: one page per defining module (regenerated on every build, so that a
# module removed from the package leaves no stale page behind) (the packages only re-export their names
# lazily, see derender.core.lazy), members from each module's __all__.
autosummary_generate = True
shutil.rmtree(DOCS / "_autosummary", ignore_errors=True)
autosummary_imported_members = False
autosummary_context = {"exports": package_exports(ROOT / "src" / "derender")}
autodoc_default_options = {"show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = False  # True would rewrite the functions' defaults, which typer reads
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False

# The figures of the architecture page, drawn at build time (no graphviz binary needed).
figures.draw_all(DOCS / "_generated")

# The gallery of real brackets (docs/gallery.md): merged at build time unless the tests already
# built it from the same sources (tests/evaluation/test_consistency.py writes the same folder).
from derender.evaluation.gallery import build_gallery  # noqa: E402

build_gallery(DOCS / "_generated", progress=lambda msg: print(msg, flush=True))


def _drop_type_docstrings(app, what, name, obj, options, lines):
    """A constant without a ``#:`` comment gets no summary rather than its type's docstring
    (``dict(**kwargs) -> new dictionary ...`` in the autosummary tables)."""
    if what in ("data", "attribute") and lines:
        type_doc = getattr(type(obj), "__doc__", None)
        if type_doc and "\n".join(lines).strip() == inspect.cleandoc(type_doc).strip():
            lines.clear()


def _keep_public_names(app, what, name, obj, skip, options):
    """Document every name of a module's ``__all__``, with or without a docstring (the API
    reference promises all public names); members of classes keep autodoc's rule."""
    if what == "module" and skip and not name.startswith("_"):
        return False
    return None


def setup(app):
    app.connect("autodoc-process-docstring", _drop_type_docstrings)
    app.connect("autodoc-skip-member", _keep_public_names)
