"""User-facing errors.

Every mistake a user can make (bad paths, inconsistent exposure times, corrupt files,
unusable stacks) raises :class:`DerenderError` (or a subclass) with a one-line message.
The CLI turns it into ``error: <message>`` on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

__all__ = [
    "DerenderError",
    "InputError",
    "StackError",
    "ModelFileError",
    "Interrupted",
]


class DerenderError(Exception):
    """A problem with the user's input or request; the message is shown as-is."""

    exit_code = 2


class InputError(DerenderError):
    """An input file or argument cannot be used (missing, corrupt, inconsistent)."""


class StackError(DerenderError):
    """An exposure stack cannot be merged (single image, all saturated, ...)."""


class ModelFileError(DerenderError):
    """A de-rendering model file is corrupt or of an incompatible version."""


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived (raised by the CLI's signal handlers). A ``BaseException``,
    like ``KeyboardInterrupt``, so that no ``except Exception`` swallows it and every
    ``finally``/cleanup on the way out runs; the CLI then says ``interrupted``, exit 130."""
