"""Command-line interface (typer): a thin shell over the library API.

Every user mistake raises :class:`~derender.core.errors.DerenderError`; :func:`main` prints
it as one line ``error: ...`` on stderr and exits with code 2 (click usage errors too).
The commands live with their stage: :mod:`derender.cli.hdr` (simulate, merge, methods,
ground truth, benchmark, demo; what ``merge`` does around the library call is in
:mod:`derender.cli.merge`), :mod:`derender.cli.evaluation` (evaluate, score, diagnose),
:mod:`derender.cli.derendering` (chart pairs, calibrate, derender, stereo),
:mod:`derender.cli.photometry` (illuminance) and :mod:`derender.cli.experiments`
(``derender experiment ...``).
"""

from __future__ import annotations

import os
import signal
import sys

import typer

from derender.cli.app import app, click_exception_types, command, fast_exit_gc
from derender.core.errors import DerenderError, Interrupted, interrupt_handler

# isort: split
# The modules register their commands; ``derender --help`` lists them in this order.
from derender.cli import derendering, hdr  # noqa: F401

# isort: split
from derender.cli import evaluation, experiments, photometry, profiles  # noqa: F401

__all__ = ["app", "main", "console_main"]


def console_main() -> None:
    """The ``derender`` process's entry point (console script, ``python -m derender.cli``):
    :func:`main`, and a failed or interrupted run leaves the process at once with its exit
    code (``os._exit`` after flushing stdout and stderr), without interpreter finalisation.
    Background threads may still be inside native code then (numba importing or loading a
    cached kernel while the frames decode, decoders, the EXR writer's compressors), and
    finalising the interpreter under them crashed the process (SIGSEGV after
    ``interrupted``: 1 in 8 to 1 in 25 interrupts early in a merge, measured). Every
    temporary output is removed before the exit code reaches this point; a successful run
    exits normally."""
    try:
        main()
    except SystemExit as exc:
        code = exc.code
        if code in (None, 0):
            raise
        status = code if isinstance(code, int) else 1
        if not isinstance(code, int):
            print(code, file=sys.stderr)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(status)


def main() -> None:
    """Console-script entry point: user errors print one line and exit with code 2;
    SIGINT/SIGTERM remove every temporary output and exit with 130 (``interrupted``)."""
    click_errors, aborts, exits = click_exception_types()
    fast_exit_gc()
    previous = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, interrupt_handler)
    except ValueError:   # not the main thread: the caller keeps its own handlers
        pass
    try:
        _run(click_errors, aborts, exits)
    finally:
        for sig, handler in previous.items():   # in-process callers (tests) get their handlers back
            signal.signal(sig, handler)


def _run(click_errors, aborts, exits) -> None:
    try:
        rv = command()(prog_name="derender", standalone_mode=False)
    except DerenderError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except (Interrupted, KeyboardInterrupt, *aborts):
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)   # a second Ctrl-C does not interrupt the exit
        typer.echo("interrupted", err=True)
        sys.exit(130)
    except exits as exc:
        sys.exit(getattr(exc, "exit_code", 0))
    except click_errors as exc:
        typer.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except MemoryError as exc:   # a step the memory checks did not foresee: every temporary is already removed
        detail = f" ({exc})" if str(exc) else ""
        typer.echo(f"error: out of memory{detail}; use fewer or smaller images, or a streamed method "
                   "(debevec, robertson, stabilized, stabilized-joint, probabilistic)", err=True)
        sys.exit(2)
    except OSError as exc:   # disk full, permissions, name too long, ... (messages name the user's paths)
        where = f": {exc.filename}" if exc.filename else ""
        typer.echo(f"error: {exc.strerror or exc}{where}", err=True)
        sys.exit(2)
    sys.exit(rv if isinstance(rv, int) else 0)




if __name__ == "__main__":  # pragma: no cover
    console_main()
