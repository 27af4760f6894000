"""Command-line interface (typer): a thin shell over the library API."""

from __future__ import annotations

import sys

import typer

from .errors import DerenderError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Recover linear scene radiance, with uncertainty, from rendered camera images.")


def main() -> None:
    """Console-script entry point: user errors print one line and exit with code 2."""
    try:
        app(standalone_mode=False)
    except DerenderError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(exc.exit_code)
