"""The ``macsplat`` command line (Typer app). Commands live one per module, each registering itself on
the app of :mod:`._app` (imported one way: this package imports the commands, never the reverse)."""

from __future__ import annotations

import sys

import typer

from . import bench, eval, export_onnx, reconstruct, render, train  # noqa: F401 - registers the commands
from ._app import app
from ._common import err_console

__all__ = ["app", "main", "run"]


def main(argv: list[str] | None = None) -> int:
    """Entry point. Usage errors become one line on stderr and exit code 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    if not args:
        args = ["--help"]
    try:
        rv = app(args=args, prog_name="macsplat", standalone_mode=False)
    except typer.Exit as e:
        return int(e.exit_code)
    except typer.Abort:
        err_console.print("aborted", style="yellow")
        return 130
    except typer.TyperException as e:  # usage errors: unknown option, bad value, missing argument
        ctx = getattr(e, "ctx", None)
        hint = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
        message = " ".join(e.format_message().split())
        err_console.print(f"[bold red]error:[/] {message}{hint}", markup=True, highlight=False, soft_wrap=True)
        return int(e.exit_code)
    return rv if isinstance(rv, int) else 0


def run() -> None:
    """Console script: ``sys.exit(main())``."""
    sys.exit(main())
