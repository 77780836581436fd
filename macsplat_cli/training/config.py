"""The settings of ``macsplat train``'s loop (:class:`~.trainer.Trainer`), checked before any work."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from .loss import LossConfig

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """Settings of the loop (the model and the data are given separately).

    Args:
        out: the run folder.
        steps: optimiser steps in all.
        batch: pairs per process and micro-step.
        accumulate: micro-steps per optimiser step.
        lr: AdamW learning rate (the paper: 1e-5).
        weight_decay: AdamW weight decay.
        warmup: linear warm-up steps, then a cosine decay to 0 at ``steps``.
        grad_clip: gradient-norm clip (0: off).
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (autocast; fp16 with a gradient scaler, CUDA only).
        val_every: validate (and keep ``best.pt``) every this many steps (0: only at the end).
        ckpt_every: write ``last.pt`` every this many steps.
        seed: seed of the data order and of everything random in the loop.
        workers: data-loader worker processes.
        max_bad_steps: non-finite losses in a row that stop the run.
        device: ``"cpu"`` or ``"cuda"``.
        loss: the objective's weights.
    """

    out: Path
    steps: int = 1000
    batch: int = 2
    accumulate: int = 1
    lr: float = 1e-5
    weight_decay: float = 0.05
    warmup: int = 50
    grad_clip: float = 0.5
    precision: str = "fp32"
    val_every: int = 100
    ckpt_every: int = 100
    seed: int = 0
    workers: int = 0
    max_bad_steps: int = 10
    device: str = "cpu"
    loss: LossConfig = field(default_factory=LossConfig)

    def validate(self) -> None:
        """Raises :class:`~macsplat_cli.errors.InputError` naming the option of a bad setting."""
        for name in ("steps", "batch", "accumulate", "max_bad_steps"):
            if getattr(self, name) < 1:
                raise InputError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(self, name)}")
        for name in ("val_every", "ckpt_every", "warmup", "workers"):
            if getattr(self, name) < 0:
                raise InputError(f"--{name.replace('_', '-')} must be ≥ 0, got {getattr(self, name)}")
        for name in ("lr", "weight_decay", "grad_clip"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"--{name.replace('_', '-')} {v}: give a finite number ≥ 0")
        if self.precision not in ("fp32", "bf16", "fp16"):
            raise InputError(f"--precision {self.precision!r}: use fp32, bf16 or fp16")
        if self.precision == "fp16" and self.device != "cuda":
            raise InputError("--precision fp16 needs --device cuda (use bf16 on the CPU)")
