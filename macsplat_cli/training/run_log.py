"""The run's metrics: ``metrics.csv`` (one row per optimiser step and per validation, appended), mirrored to
TensorBoard when it is installed (``tensorboard/`` in the run folder).

``metrics.csv`` is appended to in place (a resumed run continues it), so a link or anything but a regular file at its
name is refused rather than written through (:func:`open_for_append`).
"""

from __future__ import annotations

import csv
import logging
import os
import stat
from pathlib import Path
from typing import Any, TextIO

from ..errors import OutputPathError

__all__ = ["METRICS_FIELDS", "MetricsLog", "check_appendable", "open_for_append"]

logger = logging.getLogger(__name__)

METRICS_FIELDS = ["step", "kind", "loss", "photo", "mse", "perceptual", "mac", "matches", "lr", "seconds", "skipped",
                  "psnr", "ssim", "lpips"]  # fmt: skip
"""The columns of ``metrics.csv`` (a row fills those it has)."""


class MetricsLog:
    """Rows into ``<folder>/metrics.csv`` and, when tensorboard is installed, into ``<folder>/tensorboard``.

    Args:
        folder: the run folder.
    """

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._tensorboard: Any = None  # a SummaryWriter when tensorboard is installed, False when not

    @property
    def path(self) -> Path:
        return self.folder / "metrics.csv"

    def write(self, row: dict[str, Any]) -> None:
        """Append ``row`` (``step`` and ``kind`` — ``"train"`` or ``"val"`` — and its numbers).

        Raises:
            OutputPathError: ``metrics.csv`` could not be written, or is a link or not a regular file.
        """
        if self._tensorboard is None:
            self._tensorboard = _tensorboard_writer(self.folder)
        if self._tensorboard is not False:
            for k, v in row.items():
                if k not in ("step", "kind") and isinstance(v, (int, float)):
                    self._tensorboard.add_scalar(f"{row['kind']}/{k}", v, row["step"])
        path = self.path
        try:
            with open_for_append(path) as f:
                new = f.tell() == 0
                w = csv.DictWriter(f, fieldnames=METRICS_FIELDS, extrasaction="ignore")
                if new:
                    w.writeheader()
                w.writerow(row)
        except OSError as e:
            raise OutputPathError(f"{path}: the metrics could not be written ({e.strerror or e})") from None

    def flush(self) -> None:
        """Flush the TensorBoard writer, if one was opened."""
        if self._tensorboard:
            self._tensorboard.flush()


def check_appendable(path: Path) -> None:
    """Refuse a ``path`` that exists and is a link or not a regular file (appending would write through it)."""
    if path.is_symlink():
        raise OutputPathError(f"{path}: is a symbolic link; macsplat appends only to regular files")
    if path.exists() and not path.is_file():
        raise OutputPathError(f"{path}: exists and is not a regular file; macsplat appends only to regular files")


def open_for_append(path: Path) -> TextIO:
    """Open ``path`` to append text, refusing a link or anything but a regular file (a link planted at the name
    would be written through). ``O_NOFOLLOW`` and ``O_NONBLOCK`` (a FIFO without a reader fails instead of blocking)
    keep the refusal true when the name is swapped after :func:`check_appendable`."""
    check_appendable(path)
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    fd = os.open(path, flags, 0o666)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OutputPathError(f"{path}: exists and is not a regular file; macsplat appends only to regular files")
    return os.fdopen(fd, "a", newline="", encoding="utf-8")


def _tensorboard_writer(folder: Path) -> Any:
    """A TensorBoard writer into the run folder when tensorboard is installed (optional), else False."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        logger.debug("tensorboard is not installed: metrics go to metrics.csv only")
        return False
    return SummaryWriter(log_dir=str(folder / "tensorboard"))
