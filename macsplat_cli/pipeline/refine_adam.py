"""The refinement's optimiser: Adam as ``torch.optim.Adam`` computes it, without ``torch.optim``.

``torch.optim``'s optimisers import ``torch._dynamo`` on first use (their methods are wrapped to disable it): 1.7-1.9 s
of one core (load 4), paid by every ``--refine`` run before its first step, beside ~0.3 s a step
(benchmarks/history/refine.md). :class:`Adam` does the same arithmetic as ``torch.optim.Adam`` with its default
settings on the CPU (its single-tensor path: the same tensor operations in the same order, so the same bits; checked
in ``tests/pipeline/test_refine_adam.py``) and nothing else: no weight decay, AMSGrad, state dict or closures.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch

__all__ = ["BETAS", "EPS", "Adam"]

BETAS = (0.9, 0.999)
"""Adam's moment decay rates (``torch.optim.Adam``'s defaults, which the refinement was tuned with)."""
EPS = 1e-8
"""Added to the second moment's root (``torch.optim.Adam``'s default)."""


class Adam:
    """Adam over parameter groups: ``param_groups`` is a list of dicts, each with ``"params"`` (leaf tensors) and
    ``"lr"`` (read at every :meth:`step`, so a schedule sets it in place), and whatever else the caller keeps there
    (``"initial_lr"``)."""

    def __init__(self, groups: Iterable[dict[str, Any]]) -> None:
        self.param_groups: list[dict[str, Any]] = []
        self._state: dict[torch.Tensor, tuple[torch.Tensor, torch.Tensor, list[int]]] = {}
        for group in groups:
            self.add_param_group(group)

    def add_param_group(self, group: dict[str, Any]) -> None:
        """One more group (``"params"``, ``"lr"``)."""
        self.param_groups.append({**group, "params": list(group["params"])})

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop every parameter's gradient (``set_to_none=False``: zero it in place)."""
        for group in self.param_groups:
            for p in group["params"]:
                if set_to_none:
                    p.grad = None
                elif p.grad is not None:
                    p.grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step of every parameter that has a gradient (``torch.optim.Adam``'s ``_single_tensor_adam``)."""
        beta1, beta2 = BETAS
        for group in self.param_groups:
            lr = group["lr"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p not in self._state:
                    self._state[p] = (torch.zeros_like(p, memory_format=torch.preserve_format),
                                      torch.zeros_like(p, memory_format=torch.preserve_format), [0])  # fmt: skip
                exp_avg, exp_avg_sq, count = self._state[p]
                count[0] += 1
                step = float(count[0])
                grad = p.grad
                exp_avg.lerp_(grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                step_size = lr / (1 - beta1**step)
                denom = (exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(EPS)
                p.addcdiv_(exp_avg, denom, value=-step_size)
