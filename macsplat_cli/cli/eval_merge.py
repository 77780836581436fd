"""``macsplat eval merge SHARD... -o OUT``: the shards of one ``eval --shard I/N`` run, as the run one process writes.

The command line says ``eval merge``; Typer registers it as ``eval-merge`` (``eval`` is a command, not a group), and
:func:`macsplat_cli.cli.main` turns the first into the second.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ._app import app
from ._common import QuietOpt, VerboseOpt, check_no_clobber, command_context, err_console, escape


@app.command("eval-merge", hidden=True)
def eval_merge_command(
    ctx: typer.Context,
    shards: Annotated[list[Path], typer.Argument(metavar="SHARD...", help="The --out folders of every shard.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the merged results.")] = Path("results"),
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Merge the shards of one evaluation (eval --shard I/N) into its results, as one process would have written them.

    [bold]Example[/]

      for i in 0 1 2 3; do macsplat eval --data d/ --shard $i/4 --out shards/$i; done
      macsplat eval merge shards/* --out results/
    """
    with command_context(ctx, verbose, quiet) as state:
        from ..evaluation import ResultWriter
        from ..evaluation.shards import merge_shards

        ResultWriter.check(out)
        check_no_clobber([(f"--out {out}:", out / name) for name in ResultWriter.FILES], [])
        merged = merge_shards(list(shards), out)
        if not state.quiet:
            err_console.print(escape(f"merged {merged.shards} shards, {merged.cases} cases → {out}"), highlight=False)
