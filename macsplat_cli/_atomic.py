"""Atomic file writes: write to a temporary file beside the target, then rename.

A reader never sees a half-written file, and a failure leaves no partial output. The temporary file
is named ``.<name>.<pid>.<random>.tmp<suffix>``: one left behind by a process that was killed
(SIGKILL, a power cut) is removed by the next write of the same file, once its process is gone.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputPathError

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "check_writable", "remove_stale_temporaries"]

logger = logging.getLogger("macsplat_cli.atomic")

STALE_AFTER_S = 60.0
"""A temporary file is stale when older than this and its process is gone."""
_TMP_MIDDLE = re.compile(r"(\d+)\.[A-Za-z0-9_]+")  # "<pid>.<mkstemp's random letters>"


def check_writable(path: str | os.PathLike[str]) -> Path:
    """Fail early, before any work, if ``path`` cannot be written.

    Missing parent folders are fine (they are created when the file is written), but the
    nearest existing ancestor must be a writable folder. Returns the path.

    Raises:
        OutputPathError: ``path`` is a folder, an ancestor is a file, or the nearest
            existing ancestor is not writable.
    """
    p = Path(path)
    if p.is_dir():
        raise OutputPathError(f"cannot write {p}: it is a directory")
    ancestor = p.parent if str(p.parent) else Path(".")
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputPathError(f"cannot write {p}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OutputPathError(f"cannot write {p}: folder {ancestor} is not writable")
    return p


def _pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (one we may not signal counts as alive)."""
    if pid <= 0:
        return True  # not a process id we can judge: keep the file
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, OverflowError):
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike[str], older_than_s: float = STALE_AFTER_S) -> list[Path]:
    """Remove the temporary files that interrupted writes of ``path`` left beside it.

    Only files named like :func:`atomic_path`'s (``.<name>.<pid>.<random>.tmp<suffix>``) are
    considered, and only those older than ``older_than_s`` whose process no longer exists are
    removed: a write in progress, here or in another live process, is never touched. Returns
    the removed paths.
    """
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    prefix, suffix = f".{target.name}.", f".tmp{target.suffix}"
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        name = entry.name
        if not (name.startswith(prefix) and name.endswith(suffix) and len(name) > len(prefix) + len(suffix)):
            continue
        m = _TMP_MIDDLE.fullmatch(name[len(prefix) : len(name) - len(suffix)])
        if m is None:
            continue
        try:
            st = entry.stat(follow_symlinks=False)
            if not entry.is_file(follow_symlinks=False) or now - st.st_mtime < older_than_s:
                continue
            if _pid_alive(int(m.group(1))):
                continue
            os.unlink(entry.path)
        except OSError:
            continue
        logger.debug("removed %s, left by an interrupted write", entry.path)
        removed.append(Path(entry.path))
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The temporary name keeps the suffix of ``path`` so that writers that choose
    the format from the extension (OpenCV, Pillow) still work. On any exception
    the temporary file is removed and ``path`` is left untouched; stale temporary files of
    earlier, killed writes of ``path`` are removed first (:func:`remove_stale_temporaries`).
    """
    target = check_writable(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create folder {target.parent}: {e.strerror or e}") from None
    remove_stale_temporaries(target)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.name}.{os.getpid()}.", suffix=f".tmp{target.suffix}", dir=target.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates the file with mode 0600; give it the usual umask-based mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically (``\\n`` line endings)."""
    return atomic_write_bytes(path, text.encode("utf-8"))
