"""Checks of a merge method's option values, made when its options record is built.

Each options record (:class:`derender.hdr.classic.DebevecOptions`, ...) checks its values in
``__post_init__`` with these helpers, so that ``derender merge --option NAME=VALUE`` refuses a
bad value before any file is read (issue 37: a bad value used to be refused seconds into the
merge) and the library refuses it when the record is made.
"""

from __future__ import annotations

import difflib
from typing import Any, Iterable

from derender.core.errors import InputError

__all__ = ["check_choice", "check_at_least", "did_you_mean"]


def did_you_mean(value: Any, choices: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``choices`` to ``value``
    (:func:`difflib.get_close_matches`), or ``""`` when none is close."""
    close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_choice(name: str, value: Any, choices: Iterable[Any], *, allow_callable: bool = False) -> None:
    """Refuse ``value`` unless it is one of ``choices`` (or, ``allow_callable``, a callable)."""
    choices = tuple(choices)
    if (allow_callable and callable(value)) or value in choices:
        return
    names = ", ".join("none" if c is None else repr(c) for c in choices)
    raise InputError(f"{name} must be one of {names}, got {value!r}"
                     + did_you_mean(value, [c for c in choices if isinstance(c, str)]))


def check_at_least(name: str, value: Any, low: float, *, optional: bool = True) -> None:
    """Refuse a number below ``low`` (None passes when ``optional``)."""
    if value is None and optional:
        return
    try:
        ok = float(value) >= low
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"{name} must be a number >= {low:g}, got {value!r}")
