"""Numba kernel of the bundle adjustment's Schur complement: the points' terms summed into the camera matrix.

``H_cp H_pp⁻¹ H_pc`` is a sum over every ordered pair of observations ``(o1, o2)`` of one point of the 7 × 7 products
``Y_o1 W_o2ᵀ`` (``W``: an observation's camera-point block of ``H``, ``Y = W H_pp⁻¹``), each spread into its two
cameras' columns: ~6 pairs an observation on the orbit's tracks. NumPy spends ~0.2 s a step on it at 50,000
observations (gathers and a 49-wide scatter); this loop ~0.03 s. The NumPy twin is
:func:`.schur.schur_term_reference`; tests compare the two.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..._kernel_cache import install as _cache_with_imports
from ..._threads import JitOptions

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

__all__ = ["schur_term"]

_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}


@nb.njit(**_JIT)
def schur_term(order, starts, cc, Y, W, out):  # noqa: ANN001, ANN201
    """Add ``Y_o1 W_o2ᵀ`` of every pair of observations of each point into ``out`` [nc + 1, nc + 1] float64, at the
    columns ``cc`` [O, 7] int64 of the two observations' cameras. ``order`` [O] int64: the observations sorted by
    point, point ``p``'s at ``order[starts[p]:starts[p + 1]]``; ``Y``, ``W`` [O, 7, 3] float64."""
    for p in range(starts.shape[0] - 1):
        for a in range(starts[p], starts[p + 1]):
            o1 = order[a]
            for b in range(starts[p], starts[p + 1]):
                o2 = order[b]
                for i in range(7):
                    ci = cc[o1, i]
                    y0 = Y[o1, i, 0]
                    y1 = Y[o1, i, 1]
                    y2 = Y[o1, i, 2]
                    for j in range(7):
                        out[ci, cc[o2, j]] += y0 * W[o2, j, 0] + y1 * W[o2, j, 1] + y2 * W[o2, j, 2]


def compile_kernels() -> None:
    """Compile (or load from the cache) the kernel for the types :mod:`.schur` passes, on no points (no work)."""
    i, f = np.zeros(0, np.int64), np.zeros((0, 7, 3))
    schur_term(i, np.zeros(1, np.int64), np.zeros((0, 7), np.int64), f, f, np.zeros((1, 1)))
