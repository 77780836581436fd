"""The ``macsplat`` command line (Typer app). Commands live one per module."""

from __future__ import annotations

import sys
from typing import Annotated

import typer

from .. import __version__
from ._common import QuietOpt, State, VerboseOpt, err_console

__all__ = ["app", "main", "run"]

app = typer.Typer(
    name="macsplat",
    help="Two photos in, a 3D Gaussian splat scene out (MAC-Splat).",
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"macsplat {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    ctx: typer.Context,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Two photos in, a 3D Gaussian splat scene out (MAC-Splat)."""
    ctx.obj = State(verbose=verbose, quiet=quiet)


def _register() -> None:
    from . import bench, eval, reconstruct, render  # noqa: F401 - registers the commands


_register()


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
