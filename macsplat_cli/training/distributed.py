"""Data-parallel training over the processes ``torchrun`` starts: the process group, and what the ranks agree on.

Without ``torchrun`` (``WORLD_SIZE`` unset or 1) everything here is a single process and a no-op.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

__all__ = ["DistributedContext", "all_ranks", "barrier", "distributed_context"]


@dataclass
class DistributedContext:
    """This process's place in the launch: ``rank`` of ``world_size`` processes, ``local_rank`` on its machine."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def distributed_context(device: str) -> DistributedContext:
    """The process group of a ``torchrun`` launch (``RANK``/``WORLD_SIZE`` set), initialised; a single process
    otherwise. NCCL on CUDA, gloo on the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistributedContext()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device == "cuda" else "gloo")
    if device == "cuda":
        torch.cuda.set_device(local)
    return DistributedContext(rank, world, local)


def all_ranks(flag: bool, ctx: DistributedContext, device: torch.device) -> bool:
    """``flag`` on every process (a step is skipped everywhere when one process saw a non-finite loss)."""
    if ctx.world_size == 1:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MIN)
    return bool(t.item() > 0.5)


def barrier(ctx: DistributedContext) -> None:
    """Wait for every process (nothing to wait for in a single process)."""
    if ctx.world_size > 1:
        dist.barrier()
