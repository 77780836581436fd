"""Numba kernel of the matching stage: the best two entries of every column of a similarity block.

``torch.topk`` along the columns of a row-major ``[rows, M1]`` block walks it with a stride of ``M1``; this
kernel reads it row by row (each thread owns a range of columns) and folds the block into running results
carried across the blocks of one matrix. The plain-PyTorch twin is :func:`column_top2_update_reference`;
tests compare the two, ties included.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch

from .._kernel_cache import install as _cache_with_imports
from .._threads import JitOptions, parallel_for

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

__all__ = ["column_top2_update", "column_top2_update_reference"]


_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}


def column_top2_update(sim: np.ndarray, start: int, top: np.ndarray, arg: np.ndarray) -> None:
    """Fold the rows of ``sim`` [rows, M1] float32 (global row indices ``start …``) into the running best and
    second-best value of every column, ``top`` [2, M1] float32, and the row of the best, ``arg`` [M1] int64, in
    place. Strict comparisons: of equal values the earlier row stays best (a global argmax's choice), and
    the second best equals the best when two rows tie."""
    n_chunks = max(1, sim.shape[1] // 256)  # each chunk owns a range of at least 256 columns
    parallel_for(_chunks, n_chunks, sim, start, top, arg, n_chunks)


@nb.njit(**_JIT)
def _chunks(k0, k1, sim, start, top, arg, n_chunks):  # noqa: ANN001, ANN202
    rows, cols = sim.shape
    for k in range(k0, k1):
        c0 = k * cols // n_chunks
        c1 = (k + 1) * cols // n_chunks
        for r in range(rows):
            for c in range(c0, c1):
                v = sim[r, c]
                if v > top[0, c]:
                    top[1, c] = top[0, c]
                    top[0, c] = v
                    arg[c] = start + r
                elif v > top[1, c]:
                    top[1, c] = v


def column_top2_update_reference(sim: torch.Tensor, start: int, top: torch.Tensor, arg: torch.Tensor) -> None:
    """Same contract as :func:`column_top2_update`, on tensors (``argmax`` returns the first maximal row)."""
    best, row = sim.max(dim=0)
    second = sim.topk(2, dim=0).values[1] if sim.shape[0] > 1 else torch.full_like(best, -torch.inf)
    new = best > top[0]
    arg.copy_(torch.where(new, row + start, arg))
    top[1] = torch.where(new, torch.maximum(top[0], second), torch.maximum(top[1], best))
    top[0] = torch.where(new, best, top[0])


def compile_kernels() -> None:
    """Compile (or load from the cache) the kernel for float32 blocks, on an empty range (for a background thread)."""
    _chunks(0, 0, np.zeros((1, 1), np.float32), 0, np.zeros((2, 1), np.float32), np.zeros(1, np.int64), 1)
