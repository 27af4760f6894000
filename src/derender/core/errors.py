"""User-facing errors.

Every mistake a user can make (bad paths, inconsistent exposure times, corrupt files,
unusable stacks) raises :class:`DerenderError` (or a subclass) with a one-line message.
The CLI turns it into ``error: <message>`` on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = [
    "DerenderError",
    "InputError",
    "StackError",
    "ModelFileError",
    "Interrupted",
    "interrupt_handler",
    "interrupts_deferred",
]


class DerenderError(Exception):
    """A problem with the user's input or request; the message is shown as-is.

    The base class of :class:`InputError`, :class:`StackError` and :class:`ModelFileError`:
    catch it to handle every mistake a user can make.

    Parameters
    ----------
    message : str
        One line, shown as ``error: <message>`` by the CLI.

    Attributes
    ----------
    exit_code : int
        The CLI's exit status for this error (2).

    Examples
    --------
    >>> import derender
    >>> try:
    ...     derender.read_image("no-such-file.png")
    ... except derender.DerenderError as error:
    ...     print(type(error).__name__, error.exit_code, error)
    InputError 2 no such file: no-such-file.png
    """

    exit_code = 2


class InputError(DerenderError):
    """An input file or argument cannot be used (missing, corrupt, inconsistent).

    Parameters
    ----------
    message : str
        One line naming the input and what is wrong with it.

    Examples
    --------
    >>> import numpy as np
    >>> import derender
    >>> try:
    ...     derender.Stack(np.zeros((2, 8, 8, 3), np.float32), np.array([0.01, 0.01]))
    ... except derender.InputError as error:
    ...     print(error)
    duplicate exposure time(s): 0.01 s; every exposure needs its own time
    """


class StackError(DerenderError):
    """An exposure stack cannot be merged (single image, all saturated, ...).

    Parameters
    ----------
    message : str
        One line saying why the stack cannot be merged.

    Examples
    --------
    >>> import numpy as np
    >>> import derender
    >>> try:
    ...     derender.Stack(np.full((1, 8, 8, 3), 0.5, np.float32), np.array([0.01]))
    ... except derender.StackError as error:
    ...     print(error)
    an exposure stack needs at least two images
    """


class ModelFileError(DerenderError):
    """A de-rendering model file is corrupt or of an incompatible version.

    Parameters
    ----------
    message : str
        One line naming the file and what is wrong with it.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = os.path.join(folder, "not-a-model.npz")
    ...     np.savez(path, a=np.zeros(2))
    ...     try:
    ...         derender.load_model(path)
    ...     except derender.ModelFileError as error:
    ...         print(str(error).split(": ", 1)[1])
    not a derender model file (no format='derender-model' entry)
    """


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived (raised by the CLI's signal handlers). A ``BaseException``,
    like ``KeyboardInterrupt``, so that no ``except Exception`` swallows it and every
    ``finally``/cleanup on the way out runs; the CLI then says ``interrupted``, exit 130."""


_deferral = threading.local()
_pending: list[int] = []


def interrupt_handler(signum, _frame=None) -> None:
    """Signal handler for SIGINT/SIGTERM: raise :class:`Interrupted`, unless the main thread
    is inside :func:`interrupts_deferred`, in which case the signal is held until that block
    ends (the CLI installs it; Python runs signal handlers in the main thread only)."""
    if getattr(_deferral, "depth", 0):
        _pending.append(signum)
        return
    raise Interrupted(signal.Signals(signum).name)


@contextlib.contextmanager
def interrupts_deferred():
    """Hold back :class:`Interrupted` for a short bookkeeping step, such as creating a
    temporary output and recording it, or renaming a command's outputs into place, so that
    an interruption can fall neither between creating a file and owning it (an orphan) nor
    between two renames (a partial set of outputs). A signal that arrived meanwhile raises
    :class:`Interrupted` when the block ends. Blocking the signal with ``pthread_sigmask``
    would not do: the kernel then delivers it to another thread (NumPy's, the decoder's),
    and Python still runs the handler at once in the main thread."""
    _deferral.depth = getattr(_deferral, "depth", 0) + 1
    try:
        yield
    finally:
        _deferral.depth -= 1
        if _deferral.depth == 0 and _pending and threading.current_thread() is threading.main_thread():
            signum = _pending[-1]
            _pending.clear()
            raise Interrupted(signal.Signals(signum).name)
