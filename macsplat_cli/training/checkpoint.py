"""Writing the run's checkpoints atomically: ``best.pt`` (a predictor checkpoint) and ``last.pt`` (the same plus the
training state, built by :class:`~.trainer.Trainer`; read back by :mod:`.resume`).

A failed write leaves the previous file of that name intact and no partial file, and says why in words the user can
act on: the free space against the checkpoint's size when the disk is full. That message (and "the previous one is
intact") is why this does not use :func:`macsplat_cli._atomic.atomic_torch_save`, whose message is the generic
``cannot write <path>: the write failed (…)``.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from .._atomic import atomic_path
from ..errors import OutputPathError
from ..neural.predictor import PairPredictor
from ..neural.predictor_io import PREDICTOR_FORMAT, predictor_config

__all__ = ["predictor_payload", "state_bytes", "write_checkpoint"]


class _WriteFailed(Exception):
    """torch.save failed inside :func:`atomic_path` (carries the error out, past the removal of the temporary file)."""


def predictor_payload(predictor: PairPredictor, meta: dict[str, Any]) -> dict[str, Any]:
    """``best.pt``: a predictor checkpoint (:func:`~macsplat_cli.neural.predictor_io.save_predictor_checkpoint`'s
    layout, which ``load_pair_predictor`` reads) with the run's ``meta``."""
    return {
        "format": PREDICTOR_FORMAT,
        "version": 1,
        "config": predictor_config(predictor),
        "state_dict": {k: v.detach().cpu() for k, v in predictor.state_dict().items()},
        "meta": meta,
    }


def state_bytes(predictor: torch.nn.Module, optimizer: torch.optim.Optimizer | None = None) -> int:
    """Bytes of the predictor's tensors, and of the optimiser's state when given: about a checkpoint's size."""
    tensors = list(predictor.state_dict().values())
    if optimizer is not None:
        tensors += [v for s in optimizer.state.values() for v in s.values() if isinstance(v, torch.Tensor)]
    return sum(t.numel() * t.element_size() for t in tensors)


def write_checkpoint(path: Path, payload: dict[str, Any], *, size: Callable[[], int]) -> None:
    """``torch.save(payload)`` to ``path`` atomically.

    Args:
        path: the checkpoint file.
        payload: what to save.
        size: the checkpoint's size in bytes, asked only when a write fails for want of room.

    Raises:
        OutputPathError: it could not be written (a full disk, a folder that went away); the previous file of that
            name is intact and no partial file is left.
    """
    try:
        with atomic_path(path) as tmp:
            try:
                torch.save(payload, tmp)
            except (OSError, RuntimeError) as e:  # torch's zip writer reports a failed write as RuntimeError
                why = _write_failure(e, tmp, size)
                e.__traceback__ = None  # let go of torch's writer (and its open file) now
                raise _WriteFailed(why) from None
    except _WriteFailed as e:
        raise OutputPathError(
            f"{path}: the checkpoint could not be written ({e}); the previous one is intact"
        ) from None
    except OSError as e:  # creating or renaming the temporary file
        raise OutputPathError(
            f"{path}: the checkpoint could not be written ({e.strerror or e}); the previous one is intact"
        ) from None


def _write_failure(e: BaseException, tmp: Path, size: Callable[[], int]) -> str:
    """Why a checkpoint write failed, in words: OSError's own reason; else, when the disk lacks the room, the free
    space (once the partial ``tmp`` is removed) against the checkpoint's size; else torch's first sentence."""
    if isinstance(e, OSError):
        return str(e.strerror or e)
    need = size()
    with contextlib.suppress(OSError):
        free = shutil.disk_usage(tmp.parent).free + tmp.stat().st_blocks * 512
        if free < need:
            return f"no space left: {free / 2**20:.1f} MiB free, about {need / 2**20:.1f} MiB needed"
    first = (str(e).strip().splitlines() or [type(e).__name__])[0]
    return f"the write failed: {first[:200]}"
