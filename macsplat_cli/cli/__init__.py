"""The ``macsplat`` command line (Typer app). Commands live one per module, each registering itself on
the app of :mod:`._app` (imported one way: this package imports the commands, never the reverse).

Exit codes: 0 success, 1 internal error, 2 bad input or usage, 3 not reconstructable, 130 interrupted
(Ctrl-C, SIGINT) and 143 terminated (SIGTERM: ``kill``, ``timeout``, a container stop). SIGTERM is handled
like Ctrl-C: the command stops, the partial files of an interrupted write are removed, and the files it
had finished stay.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Iterator
from types import FrameType

import typer

from . import bench, eval, eval_merge, export_onnx, reconstruct, render, train, view  # noqa: F401 - registers the commands
from ._app import app, invocation, set_invocation
from ._common import _one_line, err_console

__all__ = ["EXIT_INTERRUPTED", "EXIT_TERMINATED", "app", "invocation", "main", "run"]

EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (SIGINT): 128 + 2."""
EXIT_TERMINATED = 143
"""Exit code after SIGTERM: 128 + 15."""


class _Terminated:
    """Set by the SIGTERM handler so that the interruption it caused exits with 143, not 130."""

    received = False


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[type[_Terminated]]:
    """While inside: SIGTERM raises KeyboardInterrupt (so ``finally`` blocks and atomic writes clean up).

    Only the main thread can install signal handlers; elsewhere (a CLI call from a worker thread)
    SIGTERM keeps its previous handling. The previous handler is restored on the way out.
    """
    _Terminated.received = False
    if threading.current_thread() is not threading.main_thread():
        yield _Terminated
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        _Terminated.received = True
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except (ValueError, OSError):  # no signals here (an embedded interpreter)
        yield _Terminated
        return
    try:
        yield _Terminated
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Entry point. Usage errors become one line on stderr and exit code 2; SIGINT exits 130, SIGTERM 143."""
    args = sys.argv[1:] if argv is None else list(argv)
    if not args:
        args = ["--help"]
    if args[:2] == ["eval", "merge"]:  # a sub-command of eval on the command line, its own command in Typer
        args = ["eval-merge", *args[2:]]
    set_invocation(args)
    with _sigterm_as_interrupt() as terminated:
        code = _main(args)
        if terminated.received and code == EXIT_INTERRUPTED:
            code = EXIT_TERMINATED
    return code


def _main(args: list[str]) -> int:
    try:
        rv = app(args=args, prog_name="macsplat", standalone_mode=False)
    except typer.Exit as e:
        return int(e.exit_code)
    except typer.Abort:
        err_console.print("aborted", style="yellow")
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:  # outside a command (while parsing the options)
        err_console.print("interrupted", style="yellow")
        return EXIT_INTERRUPTED
    except typer.TyperException as e:  # usage errors: unknown option, bad value, missing argument
        ctx = getattr(e, "ctx", None)
        hint = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
        message = _one_line(f"{e.format_message()}{hint}")
        err_console.print(f"[bold red]error:[/] {message}", markup=True, highlight=False, soft_wrap=True)
        return int(e.exit_code)
    return rv if isinstance(rv, int) else 0


def run() -> None:
    """Console script (and ``python -m macsplat_cli``): ``main()``, then the process ends at once.

    A finished command has written its files and printed its output; what is left is the interpreter's
    teardown — freeing torch's, Numba's and LLVM's objects one by one — 0.4–0.7 s of a 3–4 s ``reconstruct``.
    The streams and log handlers are flushed and the process exits with ``os._exit``, unless something may
    still need the teardown (:func:`_needs_teardown`).
    """
    code = main()
    if _needs_teardown():
        sys.exit(code)
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _needs_teardown() -> bool:
    """True when exiting without the interpreter's teardown could lose something: ``MACSPLAT_CLEAN_EXIT=1``; a
    tracer, profiler or coverage (they write their results at exit); threads other than daemons; child processes
    (data-loader workers); a torch.distributed process group (``train`` under torchrun)."""
    if os.environ.get("MACSPLAT_CLEAN_EXIT", "") not in ("", "0"):
        return True
    if sys.gettrace() is not None or sys.getprofile() is not None or "coverage" in sys.modules:
        return True
    if any(t is not threading.main_thread() and not t.daemon for t in threading.enumerate()):
        return True
    mp = sys.modules.get("multiprocessing")
    if mp is not None and mp.active_children():
        return True
    dist = sys.modules.get("torch.distributed")
    return bool(dist is not None and dist.is_available() and dist.is_initialized())
