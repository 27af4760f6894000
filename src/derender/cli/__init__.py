"""Command-line interface (typer): a thin shell over the library API.

Every user mistake raises :class:`~derender.core.errors.DerenderError`; :func:`main` prints
it as one line ``error: ...`` on stderr and exits with code 2 (click usage errors too).
The commands live with their stage: :mod:`derender.cli.hdr` (simulate, merge, evaluate,
ground truth, benchmark, demo), :mod:`derender.cli.derendering` (chart pairs, calibrate,
derender, stereo) and :mod:`derender.cli.experiments` (``derender experiment ...``).
"""

from __future__ import annotations

import sys

import typer

from derender.cli import derendering, experiments, hdr  # noqa: F401  (they register their commands)
from derender.cli.app import app, click_exception_types, fast_exit_gc
from derender.core.errors import DerenderError

__all__ = ["app", "main"]


def main() -> None:
    """Console-script entry point: user errors print one line and exit with code 2."""
    click_errors, aborts, exits = click_exception_types()
    fast_exit_gc()
    try:
        rv = app(standalone_mode=False)
    except DerenderError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except aborts:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except exits as exc:
        sys.exit(getattr(exc, "exit_code", 0))
    except click_errors as exc:
        typer.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError) as exc:
        typer.echo(f"error: {exc.strerror or exc}: {exc.filename}", err=True)
        sys.exit(2)
    sys.exit(rv if isinstance(rv, int) else 0)




if __name__ == "__main__":  # pragma: no cover
    main()
