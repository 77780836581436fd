"""Atomic file writes: write to a temporary file beside the target, then rename.

A reader never sees a half-written file, and a failure leaves no partial output. The temporary file
is named ``.<name>.<pid>.<random>.tmp<suffix>``: one left behind by a process that was killed
(SIGKILL, a power cut) is removed by the next write of the same file, once its process is gone.

**What may be replaced.** Only a regular file, or nothing. An existing output that is a symbolic
link, even one to a regular file, or anything else that is not a regular file (a device such as
``/dev/null``, a FIFO, a socket, a folder) is refused with :class:`~macsplat_cli.errors.OutputPathError`:
the rename would swap the link or the device node itself for a plain file (as root, ``--report
/dev/null`` would replace the system's ``/dev/null``), and writing *through* a link would change a
file the user did not name. One rule, easy to explain: name the file itself, or remove the link.
Links among the folders above the output are followed as usual (the user named that path).

**Errors.** Every ``OSError`` of a write (the temporary file cannot be created, ``ENOSPC``,
``EROFS``, ``EIO``, the rename fails) becomes ``OutputPathError("cannot write <path>: <reason>")``
(exit code 2), with the temporary file removed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import stat
import tempfile
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from .errors import InputError, OutputPathError

__all__ = [
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_folder",
    "check_no_clobber",
    "check_writable",
    "remove_stale_temporaries",
]

logger = logging.getLogger("macsplat_cli.atomic")

STALE_AFTER_S = 60.0
"""A temporary file is stale when older than this and its process is gone."""
_TMP_MIDDLE = re.compile(r"(\d+)\.[A-Za-z0-9_]+")  # "<pid>.<mkstemp's random letters>"


def _cannot(path: Path, e: OSError) -> OutputPathError:
    """``cannot write <path>: <strerror>`` for an OSError met while writing ``path``."""
    return OutputPathError(f"cannot write {path}: {e.strerror or e}")


def _check_entry(p: Path) -> Path:
    """The checks of :func:`check_writable` that create nothing: what exists at ``p`` and above it.

    Returns the nearest existing ancestor folder of ``p``.
    """
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        st = None
    except NotADirectoryError:  # an ancestor is a file: reported below
        st = None
    except OSError as e:
        raise OutputPathError(f"cannot write {p}: {e.strerror or e}") from None
    if st is not None:
        if stat.S_ISLNK(st.st_mode):
            try:
                to = f" (to {os.readlink(p)})"
            except OSError:
                to = ""
            raise OutputPathError(
                f"cannot write {p}: it is a symbolic link{to}; macsplat replaces only regular files, "
                "never a link or what it points to: name the file itself, or remove the link"
            )
        if stat.S_ISDIR(st.st_mode):
            raise OutputPathError(f"cannot write {p}: it is a directory")
        if not stat.S_ISREG(st.st_mode):
            raise OutputPathError(
                f"cannot write {p}: it exists and is not a regular file (a device, FIFO or socket); "
                "macsplat replaces only regular files"
            )
    ancestor = p.parent if str(p.parent) else Path(".")
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputPathError(f"cannot write {p}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OutputPathError(f"cannot write {p}: folder {ancestor} is not writable")
    return ancestor


def check_writable(path: str | os.PathLike[str]) -> Path:
    """Fail early, before any work, if ``path`` cannot be written.

    Missing parent folders are fine (they are created when the file is written), but the
    nearest existing ancestor must be a writable folder. An existing ``path`` must be a regular
    file: a symbolic link (even to a regular file), a folder, a device, a FIFO or a socket is
    refused (module docstring). The folder is then probed by creating and removing a temporary
    entry in it (a file named like :func:`atomic_path`'s, or a folder when the parent does not
    exist yet), since ``os.access`` says yes to root on read-only or virtual file systems
    (``/sys``, ``/proc``, a read-only mount). Returns the path.

    Raises:
        OutputPathError: ``path`` is a link, a folder or not a regular file, an ancestor is a
            file, or the nearest existing ancestor is not writable.
    """
    p = Path(path)
    ancestor = _check_entry(p)
    try:
        if ancestor == (p.parent if str(p.parent) else Path(".")):
            fd, probe = tempfile.mkstemp(prefix=f".{p.name}.{os.getpid()}.", suffix=f".tmp{p.suffix}", dir=ancestor)
            os.close(fd)
            os.unlink(probe)
        else:
            os.rmdir(tempfile.mkdtemp(prefix=f".macsplat.{os.getpid()}.", suffix=".probe", dir=ancestor))
    except OSError as e:
        raise OutputPathError(f"cannot write {p}: {e.strerror or e} (in {ancestor})") from None
    return p


def check_folder(path: str | os.PathLike[str]) -> Path:
    """A folder that macsplat names itself inside an output folder the user named (``coverage/``, ``runs/<setting>/``).

    It may be missing (it is created when written into), but an existing one must be a real
    folder: a symbolic link there would carry the files written into it out of what the user
    named, so it is refused, as is a file. Returns the path.

    Raises:
        OutputPathError: ``path`` is a symbolic link or not a folder.
    """
    p = Path(path)
    try:
        st = os.lstat(p)
    except (FileNotFoundError, NotADirectoryError):
        return p
    except OSError as e:
        raise OutputPathError(f"cannot write into {p}: {e.strerror or e}") from None
    if stat.S_ISLNK(st.st_mode):
        raise OutputPathError(
            f"cannot write into {p}: it is a symbolic link; macsplat writes its own subfolders only as real "
            "folders (remove the link)"
        )
    if not stat.S_ISDIR(st.st_mode):
        raise OutputPathError(f"cannot write into {p}: it exists and is not a folder")
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
    The body must only write the temporary file: an ``OSError`` it raises is reported as a
    failed write of ``path``.

    Raises:
        OutputPathError: ``path`` may not be replaced (a link, a folder, not a regular file;
            checked again just before the rename), or an ``OSError`` while creating, writing or
            renaming the temporary file (``cannot write <path>: <reason>``).
    """
    target = Path(path)
    _check_entry(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create folder {target.parent}: {e.strerror or e}") from None
    remove_stale_temporaries(target)
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.name}.{os.getpid()}.", suffix=f".tmp{target.suffix}", dir=target.parent
        )
        os.close(fd)
    except OSError as e:
        raise _cannot(target, e) from None
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates the file with mode 0600; give it the usual umask-based mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        _check_entry(target)  # a link or device put there while the body ran is not replaced either
        os.replace(tmp_path, target)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise _cannot(target, e) from None
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


def atomic_torch_save(path: str | os.PathLike[str], obj: object) -> Path:
    """``torch.save(obj)`` to ``path`` atomically and return the path.

    torch's zip writer reports a failed write (a full disk, a file-size limit) as ``RuntimeError`` ("unexpected
    pos"), not ``OSError``: both become :class:`~macsplat_cli.errors.OutputPathError`, the temporary removed and an
    existing ``path`` untouched.
    """
    import torch

    with atomic_path(path) as tmp:
        try:
            torch.save(obj, tmp)
        except RuntimeError as e:
            first = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
            e.__traceback__ = None  # let go of torch's writer (and its open file) now
            raise OutputPathError(f"cannot write {path}: the write failed ({first})") from None
    return Path(path)


def _identity(path: Path) -> tuple[str, tuple[int, int] | None]:
    """The resolved path and, when it exists, the (device, inode) of the file it names (links followed)."""
    try:
        st = os.stat(path)
        inode: tuple[int, int] | None = (st.st_dev, st.st_ino)
    except (OSError, ValueError):
        inode = None
    return os.path.realpath(path), inode


def check_no_clobber(
    outputs: Iterable[tuple[str, Path | None]], inputs: Iterable[tuple[str, Path | None]] = ()
) -> None:
    """Refuse outputs that would overwrite an input file or another output, before any work.

    Two paths are the same file when they resolve to the same path (symbolic links followed)
    or, when both exist, name the same (device, inode): hard links count too.

    Args:
        outputs: ``(label, path)`` of every file the command will write (None: not written).
        inputs: ``(label, path)`` of every file it reads (None: not given).

    Raises:
        InputError: an output is an input, or two outputs are one file.
    """
    ins = [(label, p, _identity(p)) for label, p in inputs if p is not None]
    seen: list[tuple[str, Path, tuple[str, tuple[int, int] | None]]] = []
    for label, p in outputs:
        if p is None:
            continue
        ident = _identity(p)

        def same(other: tuple[str, tuple[int, int] | None], ident: tuple = ident) -> bool:
            return ident[0] == other[0] or (ident[1] is not None and ident[1] == other[1])

        for in_label, q, q_ident in ins:
            if same(q_ident):
                raise InputError(f"{label} {p} is also the input {in_label} ({q}): refusing to overwrite an input")
        for out_label, q, q_ident in seen:
            if same(q_ident):
                raise InputError(f"two outputs point at the same file: {out_label} {q} and {label} {p}")
        seen.append((label, p, ident))
