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
        lr: learning rate (the paper: 1e-5).
        weight_decay: weight decay (decoupled with AdamW, an L2 term with Adam).
        warmup: linear warm-up steps, then the schedule.
        optimizer: ``"adamw"`` or ``"adam"`` (:mod:`.optim`).
        schedule: ``"cosine"`` (to 0 at ``steps``) or ``"step"`` (× ``lr_drop`` from ``lr_drop_at · steps`` on).
        lr_drop_at: where the step schedule drops, as a fraction of ``steps``.
        lr_drop: the step schedule's factor.
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
    optimizer: str = "adamw"
    schedule: str = "cosine"
    lr_drop_at: float = 0.5
    lr_drop: float = 0.1
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
        if self.optimizer not in ("adamw", "adam"):
            raise InputError(f"optimizer {self.optimizer!r}: use adamw or adam")
        if self.schedule not in ("cosine", "step"):
            raise InputError(f"schedule {self.schedule!r}: use cosine or step")
        if not (0.0 <= self.lr_drop_at <= 1.0 and 0.0 <= self.lr_drop <= 1.0):
            raise InputError(f"lr_drop_at {self.lr_drop_at} and lr_drop {self.lr_drop}: both must be in [0, 1]")
        if self.precision not in ("fp32", "bf16", "fp16"):
            raise InputError(f"--precision {self.precision!r}: use fp32, bf16 or fp16")
        if self.precision == "fp16" and self.device != "cuda":
            raise InputError("--precision fp16 needs --device cuda (use bf16 on the CPU)")
