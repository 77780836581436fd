"""Numba twins of :func:`macsplat_cli.sh.eval_sh`'s basis and its derivative, for the fused projection kernels.

Same constants and term order as ``sh.py`` (the real SH basis of 3DGS and gsplat), degrees 0–3, in float64.
"""

from __future__ import annotations

import numba as nb

from .._kernel_cache import install as _cache_with_imports
from .._threads import JitOptions
from ..sh import C0, C1, C2, C3

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


@nb.njit(**_JIT)
def sh_basis(x, y, z, out):  # noqa: ANN001, ANN202
    """The first ``len(out)`` (1, 4, 9 or 16) basis functions at the unit direction ``(x, y, z)`` into ``out``."""
    k = out.shape[0]
    xx, yy, zz = x * x, y * y, z * z
    out[0] = C0
    if k > 1:
        out[1], out[2], out[3] = -C1 * y, C1 * z, -C1 * x
    if k > 4:
        out[4] = C2[0] * x * y
        out[5] = C2[1] * y * z
        out[6] = C2[2] * (2.0 * zz - xx - yy)
        out[7] = C2[3] * x * z
        out[8] = C2[4] * (xx - yy)
    if k > 9:
        out[9] = C3[0] * y * (3.0 * xx - yy)
        out[10] = C3[1] * x * y * z
        out[11] = C3[2] * y * (4.0 * zz - xx - yy)
        out[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        out[13] = C3[4] * x * (4.0 * zz - xx - yy)
        out[14] = C3[5] * z * (xx - yy)
        out[15] = C3[6] * x * (xx - 3.0 * yy)


@nb.njit(inline="always", **_JIT)
def sh_basis_vjp(x, y, z, out):  # noqa: ANN001, ANN202
    """The gradients ``d basis_k / d (x, y, z)`` of :func:`sh_basis` into ``out`` [K, 3] (row 0, a constant, is not
    written)."""
    k = out.shape[0]
    xx, yy, zz = x * x, y * y, z * z
    if k == 1:
        return
    out[1, 0], out[1, 1], out[1, 2] = 0.0, -C1, 0.0
    out[2, 0], out[2, 1], out[2, 2] = 0.0, 0.0, C1
    out[3, 0], out[3, 1], out[3, 2] = -C1, 0.0, 0.0
    if k > 4:
        out[4, 0], out[4, 1], out[4, 2] = C2[0] * y, C2[0] * x, 0.0
        out[5, 0], out[5, 1], out[5, 2] = 0.0, C2[1] * z, C2[1] * y
        out[6, 0], out[6, 1], out[6, 2] = -2.0 * C2[2] * x, -2.0 * C2[2] * y, 4.0 * C2[2] * z
        out[7, 0], out[7, 1], out[7, 2] = C2[3] * z, 0.0, C2[3] * x
        out[8, 0], out[8, 1], out[8, 2] = 2.0 * C2[4] * x, -2.0 * C2[4] * y, 0.0
    if k > 9:
        out[9, 0], out[9, 1], out[9, 2] = C3[0] * 6.0 * x * y, C3[0] * 3.0 * (xx - yy), 0.0
        out[10, 0], out[10, 1], out[10, 2] = C3[1] * y * z, C3[1] * x * z, C3[1] * x * y
        out[11, 0], out[11, 2] = -2.0 * C3[2] * x * y, 8.0 * C3[2] * y * z
        out[11, 1] = C3[2] * (4.0 * zz - xx - 3.0 * yy)
        out[12, 0], out[12, 1] = -6.0 * C3[3] * x * z, -6.0 * C3[3] * y * z
        out[12, 2] = C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy)
        out[13, 1], out[13, 2] = -2.0 * C3[4] * x * y, 8.0 * C3[4] * x * z
        out[13, 0] = C3[4] * (4.0 * zz - 3.0 * xx - yy)
        out[14, 0], out[14, 1], out[14, 2] = 2.0 * C3[5] * x * z, -2.0 * C3[5] * y * z, C3[5] * (xx - yy)
        out[15, 0], out[15, 1], out[15, 2] = C3[6] * 3.0 * (xx - yy), -6.0 * C3[6] * x * y, 0.0
