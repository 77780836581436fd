"""The refinement's optimiser: Adam as ``torch.optim.Adam`` computes it, without ``torch.optim``.

``torch.optim``'s optimisers import ``torch._dynamo`` on first use (their methods are wrapped to disable it): 1.7-1.9 s
of one core (load 4), paid by every ``--refine`` run before its first step, beside ~0.3 s a step
(benchmarks/history/refine.md). :class:`Adam` does the same arithmetic as ``torch.optim.Adam`` with its default
settings on the CPU (its single-tensor path: the same tensor operations in the same order, so the same bits; checked
in ``tests/pipeline/test_refine_adam.py``) and nothing else: no weight decay, AMSGrad, state dict or closures.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["BETAS", "EPS", "Adam"]

BETAS = (0.9, 0.999)
"""Adam's moment decay rates (``torch.optim.Adam``'s defaults, which the refinement was tuned with)."""
EPS = 1e-8
"""Added to the second moment's root (``torch.optim.Adam``'s default)."""


@dataclass
class _State:
    """One parameter's moments (``exp_avg``, ``exp_avg_sq``), the buffer its denominator is written into, its steps."""

    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor
    denom: torch.Tensor
    steps: int = 0


class Adam:
    """Adam over parameter groups: ``param_groups`` is a list of dicts, each with ``"params"`` (leaf tensors) and
    ``"lr"`` (read at every :meth:`step`, so a schedule sets it in place), and whatever else the caller keeps there
    (``"initial_lr"``)."""

    def __init__(self, groups: Iterable[dict[str, Any]]) -> None:
        self.param_groups: list[dict[str, Any]] = []
        self._state: dict[torch.Tensor, _State] = {}
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
        """One Adam step of every parameter that has a gradient: ``torch.optim.Adam``'s ``_single_tensor_adam``
        arithmetic, op for op, applied with ``torch._foreach_*`` to the parameters of a group at the same step count
        (one call per op instead of one per tensor), the denominator written into a buffer kept per parameter (a
        fresh one each step costs page faults on large maps)."""
        for group in self.param_groups:
            by_count: dict[int, list[torch.Tensor]] = {}
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p not in self._state:
                    m, v, d = (torch.zeros_like(p, memory_format=torch.preserve_format) for _ in range(3))
                    self._state[p] = _State(m, v, d)
                state = self._state[p]
                state.steps += 1
                by_count.setdefault(state.steps, []).append(p)
            for count, ps in by_count.items():
                self._update(ps, float(count), group["lr"])

    def _update(self, ps: list[torch.Tensor], step: float, lr: float) -> None:
        """Adam's update of parameters ``ps`` at their ``step``-th step with rate ``lr``."""
        beta1, beta2 = BETAS
        grads = [p.grad for p in ps if p.grad is not None]
        states = [self._state[p] for p in ps]
        exp_avg, exp_avg_sq, denom = ([s.exp_avg for s in states], [s.exp_avg_sq for s in states],
                                      [s.denom for s in states])  # fmt: skip
        torch._foreach_lerp_(exp_avg, grads, 1 - beta1)
        torch._foreach_mul_(exp_avg_sq, beta2)
        torch._foreach_addcmul_(exp_avg_sq, grads, grads, value=1 - beta2)
        step_size = lr / (1 - beta1**step)
        for d, v in zip(denom, exp_avg_sq):
            torch.sqrt(v, out=d)
        torch._foreach_div_(denom, (1 - beta2**step) ** 0.5)
        torch._foreach_add_(denom, EPS)
        torch._foreach_addcdiv_(ps, exp_avg, denom, value=-step_size)
