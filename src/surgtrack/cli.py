"""Command-line interface: thin wrappers over the library (one command a workflow, DESIGN.md section 1)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from .io import SequenceError

app = typer.Typer(help="CAD-free 6-DoF tracking and reconstruction of surgical instruments from RGB-D video.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)


def fail(message: str) -> None:
    """Print a one-line error and exit non-zero."""
    typer.secho(f"surgtrack: error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2)


def main() -> None:
    try:
        app()
    except SequenceError as e:
        print(f"surgtrack: error: {e}", file=sys.stderr)
        sys.exit(2)


_ = (Path, Annotated)  # used by the commands below
