"""Numerics shared by the tests: rounding-error bounds from the arithmetic (unit roundoff, Higham's γₙ, the forward
error of a network's layers), the rotation conversions' rounding budgets, a bounded comparison, gradcheck settings.

A tolerance built from these holds on every CPU and thread count (see ``.ci/run``: the numerics-sensitive tests run a
second time under the portable kernels)."""

from __future__ import annotations

import math

import numpy as np
import torch

# torch.autograd.gradcheck settings of the analytic-gradient tests (float64): step, absolute and relative tolerance.
GC_EPS = 1e-6
GC_ATOL = 1e-5
GC_RTOL = 1e-3


def max_rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| / max |b| (0 when both are empty or zero)."""
    a, b = a.detach(), b.detach()
    if b.numel() == 0:
        return 0.0
    scale = float(b.abs().max())
    return float((a - b).abs().max()) / scale if scale > 0 else float((a - b).abs().max())


def unit_roundoff(dtype: torch.dtype | np.dtype | type) -> float:
    """u = eps / 2: the largest relative error of one rounded operation in ``dtype``."""
    if isinstance(dtype, torch.dtype):
        return torch.finfo(dtype).eps / 2
    return float(np.finfo(dtype).eps) / 2


def gamma(n: int, dtype: torch.dtype | np.dtype | type) -> float:
    """Higham's γₙ = n·u / (1 − n·u): |fl(Σ xᵢyᵢ) − Σ xᵢyᵢ| ≤ γₙ Σ |xᵢyᵢ| for a sum of n products in any order.

    The bound holds whatever the summation order, blocking or vector width of the kernel, so a tolerance built
    from it holds on every CPU (SSE, AVX2, AVX-512, NEON) and thread count; two results computed in different
    orders differ by at most twice it.
    """
    u = unit_roundoff(dtype)
    assert n * u < 1, "γₙ needs n·u < 1"
    return n * u / (1 - n * u)


def _as_f64(x) -> np.ndarray:  # noqa: ANN001
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def assert_within(actual, expected, bound, what: str = "") -> None:  # noqa: ANN001
    """``|actual − expected| ≤ bound`` elementwise, compared in float64 (tensors or arrays; ``bound`` is a scalar or
    broadcasts, e.g. one derived bound per element). The message gives the worst element and its bound."""
    a, e = np.broadcast_arrays(_as_f64(actual), _as_f64(expected))
    b = np.broadcast_to(_as_f64(bound), a.shape)
    assert a.shape == e.shape, f"{what}: shapes {a.shape} and {e.shape}"
    err = np.abs(a - e)
    bad = ~(err <= b)  # NaN fails too
    if bad.any():
        ratio = np.where(bad, err / np.where(b > 0, b, np.finfo(float).tiny), -1.0)
        i = np.unravel_index(int(np.argmax(ratio)), a.shape)
        raise AssertionError(
            f"{what}: {int(bad.sum())} of {a.size} elements exceed the bound; worst at {tuple(int(k) for k in i)}: "
            f"|{float(a[i])!r} − {float(e[i])!r}| = {err[i]:.3e} > {b[i]:.3e}"
        )


def dot_lengths(module: torch.nn.Module) -> list[int]:
    """The number of terms of the dot products in ``module``'s layers: fan-in of each Linear and convolution, and
    two sums (mean, variance) over the normalised size of each LayerNorm/GroupNorm."""
    out: list[int] = []
    for m in module.modules():
        if isinstance(m, torch.nn.Linear):
            out.append(m.in_features)
        elif isinstance(m, (torch.nn.Conv1d, torch.nn.Conv2d, torch.nn.Conv3d)):
            out.append(m.in_channels // m.groups * math.prod(m.kernel_size))
        elif isinstance(m, (torch.nn.ConvTranspose1d, torch.nn.ConvTranspose2d, torch.nn.ConvTranspose3d)):
            out.append(m.in_channels // m.groups * math.prod(m.kernel_size))  # an upper bound of the fan-in
        elif isinstance(m, torch.nn.LayerNorm):
            out += [math.prod(m.normalized_shape)] * 2
        elif isinstance(m, torch.nn.GroupNorm):
            out += [m.num_channels // m.num_groups] * 2
    return out


def forward_rel_tol(module: torch.nn.Module, *sums: int, dtype: torch.dtype = torch.float32) -> float:
    """A first-order estimate of a forward pass's relative rounding error: ``Σ_l γ(n_l)`` over every dot product
    of the network (:func:`dot_lengths`) and the extra ``sums`` (e.g. attention's ``QKᵀ`` over the head size and
    ``softmax·V`` over the tokens, once per attention layer), each layer taken to pass its input's relative error
    on with unit gain (normalisations and residual connections keep activations O(1)).

    Not a rigorous a-priori bound for a deep network, but the worst case of every layer's rounding at once: two
    evaluations in different orders differ by up to twice it, one against a float64 reference by up to it. Compare
    with :func:`max_rel_err` (relative to the largest magnitude, so a cancelling element is not over-weighted)."""
    return sum(gamma(n, dtype) for n in [*dot_lengths(module), *sums])


def forward_rel_tol_probabilistic(
    module: torch.nn.Module, *sums: int, dtype: torch.dtype = torch.float32, lam: float = 8.0
) -> float:
    """:func:`forward_rel_tol` with each layer's γ(n) replaced by the probabilistic bound λ·√n·u (Higham & Mary,
    SIAM J. Sci. Comput. 41(5), 2019: with independent rounding errors, a sum of n terms is within λ√n·u·Σ|terms|
    except with probability ≤ 2n·exp(−λ²(1 − u)²/2); λ = 8: < 1e-12 per 4608-term dot). For wide layers, where the
    worst case n·u is √n times too pessimistic to leave a meaningful tolerance."""
    u = unit_roundoff(dtype)
    return sum(lam * math.sqrt(n) * u for n in [*dot_lengths(module), *sums])


# Rounding budgets of the rotation conversions (macsplat_cli.rotations and NumPy twins), in units of the unit
# roundoff u of the working precision, first order (derivations in tests/test_rotations.py):
ROT_UNIT_Q = 4  # a normalised quaternion q/‖q‖, per component; and ‖q̂‖ − 1
ROT_MAT = 16  # R(q̂) per entry, off a rotation (its own 8u, plus 2·(‖q̂‖² − 1))
ROT_QUAT = 13 + ROT_MAT  # Shepperd's R → q per component, for an R within ROT_MAT of a rotation
ROT_ROUND_TRIP = 2 * math.sqrt(2) * 2 * ROT_QUAT + ROT_MAT  # R → q → R per entry (a rotation by ≤ 2‖δq‖)
