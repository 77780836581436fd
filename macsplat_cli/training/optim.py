"""The optimiser and the learning-rate schedule of ``macsplat train`` (:class:`~.config.TrainConfig`'s
``optimizer``, ``schedule``, ``warmup``, ``lr_drop_at`` and ``lr_drop``).

* ``adamw`` (decoupled weight decay, the paper's) or ``adam`` (L2 weight decay coupled into the gradient, the
  MAC-Splat release's — which passes no decay at all);
* ``cosine``: linear warm-up over ``warmup`` steps, then a cosine decay to 0 at ``steps``; ``step``: the warm-up,
  then the rate times ``lr_drop`` from step ``round(lr_drop_at · steps)`` on (the release's ``MultiStepLR``: ×0.1
  at epoch 5 of 10).

Both schedules are one :class:`torch.optim.lr_scheduler.LambdaLR` whose state is its step count, so a resumed run
continues on the same curve.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch

from .config import TrainConfig

__all__ = ["build_optimizer", "build_scheduler", "lr_factor"]


def lr_factor(step: int, config: TrainConfig) -> float:
    """The learning rate of optimiser step ``step`` (0-based) as a fraction of ``config.lr``."""
    warmup, total = config.warmup, config.steps
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    if config.schedule == "step":
        return config.lr_drop if step >= round(config.lr_drop_at * total) else 1.0
    progress = (step - warmup) / max(1, total - warmup)
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


def build_optimizer(params: Iterable[torch.nn.Parameter], config: TrainConfig) -> torch.optim.Optimizer:
    """``config.optimizer`` over ``params`` at ``config.lr`` with ``config.weight_decay``."""
    cls = torch.optim.AdamW if config.optimizer == "adamw" else torch.optim.Adam
    return cls(list(params), lr=config.lr, weight_decay=config.weight_decay)


def build_scheduler(optimizer: torch.optim.Optimizer, config: TrainConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """The schedule of :func:`lr_factor` on ``optimizer``."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, config))
