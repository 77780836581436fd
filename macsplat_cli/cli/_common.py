"""Shared CLI plumbing: consoles, common options, and turning errors into exit codes."""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape

from .._atomic import check_no_clobber
from .._log import remove_logging, setup_logging
from ..errors import MacsplatError

__all__ = [
    "QuietOpt",
    "StageProgress",
    "State",
    "VerboseOpt",
    "check_no_clobber",
    "command_context",
    "err_console",
    "escape",
    "expand_photos",
    "out_console",
]

logger = logging.getLogger("macsplat_cli.cli")

err_console = Console(stderr=True, highlight=False)
"""Human-facing output: logs, progress, summaries."""
out_console = Console(highlight=False, soft_wrap=True)
"""Machine-readable output (``--json``) only."""

VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging, and tracebacks on errors.")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="Only warnings and errors; no progress or summary.")]


@dataclass
class State:
    """Options given before the command name (``macsplat -v render ...``)."""

    verbose: bool = False
    quiet: bool = False


MAX_ERROR_CHARS = 2000
"""An error line is cut to this many characters: a message may quote a name from a file (megabytes, at worst)."""


def _one_line(msg: str) -> str:
    """The message on one line, at most :data:`MAX_ERROR_CHARS` characters ("…" where cut), escaped for Rich
    markup (paths and values may hold ``[...]``)."""
    line = " ".join(str(msg).split())
    return escape(line if len(line) <= MAX_ERROR_CHARS else line[: MAX_ERROR_CHARS - 1] + "…")


def _log_warning(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, file: object = None,
    line: str | None = None,
) -> None:  # fmt: skip
    """``warnings.showwarning`` for CLI commands: one DEBUG line naming the category and where it came from."""
    logger.debug("%s from %s:%d: %s", category.__name__, Path(filename).name, lineno, " ".join(str(message).split()))


@contextlib.contextmanager
def command_context(ctx: typer.Context, verbose: bool, quiet: bool) -> Iterator[State]:
    """Set up logging for a command and convert its errors into one line and an exit code.

    * :class:`MacsplatError` → ``error: <message>`` and the error's exit code (2 bad input,
      3 not reconstructable);
    * any other exception → ``internal error: ...`` and exit code 1;
    * with ``--verbose`` the traceback is printed as well.

    Python warnings of the libraries underneath (NumPy, Pillow, OpenCV's bindings, torch) become DEBUG log lines
    (shown with ``--verbose``) instead of raw multi-line text on stderr: what the user needs to know is said by
    macsplat's own log lines and errors.
    """
    root = ctx.find_root().obj if ctx.find_root().obj is not None else State()
    state = State(verbose=verbose or root.verbose, quiet=(quiet or root.quiet) and not (verbose or root.verbose))
    setup_logging(err_console, verbose=state.verbose, quiet=state.quiet)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")  # each distinct warning once per place, as Python shows them
            warnings.showwarning = _log_warning
            yield state
    except (typer.Exit, typer.Abort):
        raise
    except MacsplatError as e:
        if state.verbose:
            err_console.print_exception()
        err_console.print(f"[bold red]error:[/] {_one_line(str(e))}", markup=True, highlight=False, soft_wrap=True)
        raise typer.Exit(code=e.exit_code) from None
    except KeyboardInterrupt:
        err_console.print("interrupted", style="yellow")
        raise typer.Exit(code=130) from None
    except Exception as e:  # noqa: BLE001 - the one place where unexpected errors become exit codes
        if state.verbose:
            err_console.print_exception()
        err_console.print(
            f"[bold red]internal error:[/] {escape(type(e).__name__)}: {_one_line(str(e))} "
            "(run with --verbose for the traceback)",
            markup=True,
            highlight=False,
            soft_wrap=True,
        )
        raise typer.Exit(code=1) from None
    finally:
        remove_logging()


class StageProgress:
    """One line per stage: a spinner while it runs, then a tick and its wall time."""

    def __init__(self, disabled: bool, also: Callable[[str, str], None] | None = None) -> None:
        """``also``: called with every event too (``reconstruct --profile``)."""
        from rich.progress import Progress, SpinnerColumn, TextColumn
        from rich.text import Text

        class StateColumn(SpinnerColumn):
            """The spinner while a stage runs, a tick when it ends, a red cross when it fails."""

            def render(self, task: Any) -> Any:
                return Text("✗", style="red") if task.fields.get("failed") else super().render(task)

        self.progress = Progress(
            StateColumn(finished_text="[green]✓[/]"), TextColumn("{task.description:<22}"),
            TextColumn("{task.fields[took]}"), console=err_console, disable=disabled, transient=False,
        )  # fmt: skip
        self.tasks: dict[str, Any] = {}
        self.started: dict[str, float] = {}
        self.also = also

    def __enter__(self) -> StageProgress:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        for stage, task in self.tasks.items():  # a stage interrupted by an error stops its spinner
            if stage in self.started:
                self.progress.update(task, took="[red]failed[/]", failed=True)
            self.progress.stop_task(task)
        self.progress.stop()

    def refine_step(self, step: int, steps: int, terms: dict[str, float]) -> None:
        """A refinement step: its loss terms on the refine line."""
        mac = f", mac {terms['mac']:.4f}" if "mac" in terms else ""
        mac += f", lpips {terms['lpips']:.4f}" if "lpips" in terms else ""
        task = self.tasks.get("refine")
        if task is not None:
            self.progress.update(task, took=f"step {step}/{steps}: photo {terms['photo']:.4f}{mac}")

    def event(self, stage: str, kind: str) -> None:
        import time

        if self.also is not None:
            self.also(stage, kind)

        if kind == "start":
            self.started[stage] = time.perf_counter()
            self.tasks[stage] = self.progress.add_task(stage, total=1, took="", failed=False)
        elif kind == "fail":
            self.started.pop(stage, None)
            self.progress.update(self.tasks[stage], took="[red]failed[/]", failed=True)
            self.progress.stop_task(self.tasks[stage])
        else:
            took = time.perf_counter() - self.started.pop(stage)
            self.progress.update(self.tasks[stage], completed=1, took=f"{took:.2f} s")
            self.progress.stop_task(self.tasks[stage])


_GLOB = set("*?[")


def expand_photos(args: Iterable[Path]) -> list[Path]:
    """The photos named on the command line: a folder gives its image files (sorted by name, not recursive), an
    unexpanded glob pattern (``'photos/*.jpg'``) its matches (sorted); the engine checks the count
    (:func:`~macsplat_cli.engine.reconstruct`, before any weights load).

    Raises:
        InputError: a folder or pattern with no photos.
    """
    import glob

    from ..errors import InputError
    from ..images import IMAGE_FORMATS

    out: list[Path] = []
    for a in args:
        if a.is_dir():
            found = sorted(p for p in a.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_FORMATS)
            if not found:
                raise InputError(f"{a}: a folder with no photos ({', '.join(IMAGE_FORMATS)})")
            out += found
        elif not a.exists() and _GLOB & set(str(a)):
            found = sorted(Path(p) for p in glob.glob(str(a)) if Path(p).suffix.lower() in IMAGE_FORMATS)
            if not found:
                raise InputError(f"{a}: no photo matches this pattern")
            out += found
        else:
            out.append(a)
    return out
