"""The command line in this process: ``macsplat ARGS`` with its output captured, its one ``error:`` line, and a
file-size limit under which writes fail as on a full disk."""

from __future__ import annotations

import contextlib
import io
import resource
import signal
from collections.abc import Iterator

from macsplat_cli.cli import main


def run_cli(args: list) -> tuple[int, str, str]:  # noqa: ANN001 - paths or strings
    """``macsplat ARGS`` in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


def run_captured(capsys, *args) -> tuple[int, str, str]:  # noqa: ANN001 - pytest's capsys; paths or strings
    """``macsplat ARGS`` in this process, its output read back through pytest's ``capsys``: (exit code, stdout,
    stderr)."""
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def one_error_line(err: str) -> str:
    """The one ``error:`` line of a command's stderr (asserts there is exactly one)."""
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


@contextlib.contextmanager
def file_size_limit(n_bytes: int) -> Iterator[None]:
    """Within it, writes past ``n_bytes`` in a file fail in this process (EFBIG), as on a full disk (SIGXFSZ
    ignored meanwhile)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (n_bytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
