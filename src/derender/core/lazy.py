"""Lazy re-exports for the subpackages (PEP 562), so that ``import derender`` stays fast.

Each stage's ``__init__`` lists its modules' public names; a name is imported on first
access. Why our own and not ``lazy_loader``: twenty lines, no dependency, and the same
behaviour for ``dir()`` and ``from derender.hdr import merge``.
"""

from __future__ import annotations

import importlib
from typing import Callable

__all__ = ["attach"]


def attach(package: str, modules: dict[str, list[str]]) -> tuple[Callable, Callable, list[str]]:
    """``(__getattr__, __dir__, __all__)`` for ``package`` exporting ``modules[m]`` names of ``package.m``."""
    where = {name: mod for mod, names in modules.items() for name in names}

    def __getattr__(name: str):
        if name in modules and "." not in name:
            return importlib.import_module(f"{package}.{name}")
        mod = where.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{mod}"), name)

    def __dir__() -> list[str]:
        return sorted(set(where) | {m for m in modules if "." not in m})

    return __getattr__, __dir__, sorted(where)
