"""The settings of ``macsplat train`` (a recipe's and the loop's), checked before any work."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from .loss import LossConfig

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """Every setting of a training run: what a recipe fixes (:mod:`.recipes`; the defaults are the ``paper``
    recipe's) and the loop's own. The model's files and the data are given separately (:class:`~.runner.TrainSpec`).

    Args:
        out: the run folder.
        recipe: the recipe these values started from (``paper`` or ``released-code``; a resumed run keeps it).
        steps: optimiser steps in all (unless ``steps_per_scene``).
        steps_per_scene: when set, the run's steps are this × the training scenes ÷ the processes
            (:meth:`steps_for`; the release: 10 epochs × 20 samples a scene).
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
        loss: the objective (:class:`~.loss.LossConfig`, with its :class:`~macsplat_cli.mac.MACConfig`).
        size: ``(W, H)`` of the training frames.
        crop: ``centre`` or ``principal-point`` (:class:`~.data.PairSamplingConfig`).
        targets: target views per sample.
        per_scene: samples per scene and epoch, drawn scene first (None: every candidate pair once an epoch).
        max_scale: cap of the Gaussians' scales (None: none), kept in the checkpoint.
        dino_variant: DINOv3 variant of a ``--model full --init random`` model (with ``--dino``, the file's).
        exclude_scenes: scenes left out of training and validation.
    """

    out: Path
    recipe: str = "paper"
    steps: int = 1000
    steps_per_scene: int | None = None
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
    size: tuple[int, int] = (256, 192)
    crop: str = "centre"
    targets: int = 2
    per_scene: int | None = None
    max_scale: float | None = None
    dino_variant: str = "vitl16"
    exclude_scenes: tuple[str, ...] = ()

    def steps_for(self, scenes: int, world_size: int) -> int:
        """The run's steps: ``steps``, or ``steps_per_scene · scenes / world_size`` rounded up."""
        if self.steps_per_scene is None:
            return self.steps
        return max(1, -(-self.steps_per_scene * scenes // max(1, world_size)))

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
