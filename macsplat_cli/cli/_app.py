"""The Typer app every command registers on, and its root options."""

from __future__ import annotations

from typing import Annotated

import typer

from .. import __version__
from ._common import QuietOpt, State, VerboseOpt

__all__ = ["app"]

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


_INVOCATION: list[str] = []


def set_invocation(args: list[str]) -> None:
    """Remember the arguments of the command running in this process (``eval --jobs`` starts its shards with them)."""
    _INVOCATION[:] = [str(a) for a in args]


def invocation() -> list[str]:
    """The arguments :func:`macsplat_cli.cli.main` was given (the command name first)."""
    return list(_INVOCATION)
