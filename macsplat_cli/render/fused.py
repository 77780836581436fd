"""The fused projection: :func:`~.projection.project_gaussians` as one Numba kernel with a hand-written backward.

Same contract, arithmetic, culls and order as the plain-PyTorch twin in ``projection.py`` (which stays the reference
the tests compare it with, values and every gradient); one ``torch.autograd.Function`` instead of ~40 element-wise
ops and their autograd graph. The camera is a constant here: a ``viewmat`` or ``K`` that requires a gradient goes
through the twin (see :func:`camera_needs_grad`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from ..gaussians import Gaussians
from . import _kernels, _project_kernels, _workspace
from .composite import TILE_SIZE
from .constants import ALPHA_MIN
from .projection import MAX_SCREEN_STD, Projection

__all__ = ["camera_needs_grad", "project_gaussians_fused", "render_fused"]


def camera_needs_grad(viewmat: torch.Tensor, K: torch.Tensor) -> bool:
    """Whether the camera takes part in autograd (the fused kernel gives no camera gradient)."""
    return torch.is_grad_enabled() and (viewmat.requires_grad or K.requires_grad)


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


def _camera(viewmat: torch.Tensor, K: torch.Tensor, dtype: torch.dtype, width: int, height: int, near: float,
            far: float, eps2d: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The kernels' ``(cam [20], lim [10])`` float64 arrays (layout: ``_project_kernels``), from the camera rounded
    to the Gaussians' ``dtype`` as the twin sees it; the cull thresholds rounded to ``dtype`` too, as the twin
    compares them."""
    V = viewmat.detach().to(dtype).double().cpu().numpy()
    k = K.detach().to(dtype).double().cpu().numpy()
    R, t = V[:3, :3], V[:3, 3]
    fx, skew, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    cam = np.concatenate([R.reshape(-1), t, [fx, skew, cx, fy, cy], -(R.T @ t)])
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    f_max = max(abs(fx), abs(fy)) + abs(skew)

    def rounded(v: float) -> float:
        return float(torch.tensor(v, dtype=dtype))

    logit_min = math.log(ALPHA_MIN / (1.0 - ALPHA_MIN))
    lim = np.array(
        [
            -(cx / fx + 0.3 * tan_x),
            (width - cx) / fx + 0.3 * tan_x,
            -(cy / fy + 0.3 * tan_y),
            (height - cy) / fy + 0.3 * tan_y,
            rounded(near),
            rounded(far),
            eps2d,
            rounded(logit_min),
            math.log(MAX_SCREEN_STD / f_max),
            float(4 * max(width, height) + 16),
        ]  # fmt: skip
    )
    return np.ascontiguousarray(cam), lim


def _cotangents(m: int, dtype: np.dtype, *vs: torch.Tensor | None) -> np.ndarray:
    """The projection backward's cotangent rows [M, 10] (``_project_kernels.COT_COLS``) from those of the mean 2D
    [M, 2], conic [M, 3], opacity [M] and features [M, 4] (None: zero)."""
    cot = _workspace.zeros((m, _project_kernels.COT_COLS), dtype)
    col = 0
    for v, width in zip(vs, (2, 3, 1, 4)):
        if v is not None:
            cot[:, col : col + width] = _np(v).reshape(m, width)
        col += width
    return cot


class _Project(torch.autograd.Function):
    """Gaussian parameters → the kept Gaussians' ``(ids, means2d, conics, opacities, features, rect)``
    (``_project_kernels.project``), differentiable w.r.t. the parameters."""

    @staticmethod
    def forward(  # noqa: ANN205 - autograd signature
        ctx,  # noqa: ANN001
        means: torch.Tensor,
        log_scales: torch.Tensor,
        quats: torch.Tensor,
        opacity_logits: torch.Tensor,
        sh: torch.Tensor,
        cam: np.ndarray,
        lim: np.ndarray,
        size: tuple[int, int],
    ):
        arrays = tuple(_np(t) for t in (means, log_scales, quats, opacity_logits, sh))
        outs = _project_kernels.project(*arrays + (cam, lim, size[0], size[1]))
        ctx.arrays, ctx.cam, ctx.lim, ctx.ids, ctx.device = arrays, cam, lim, outs[0], means.device
        ids, *rest, rect = (torch.from_numpy(a).to(means.device) for a in outs)
        ctx.mark_non_differentiable(ids, rect)
        return (ids, *rest, rect)

    @staticmethod
    @once_differentiable
    def backward(ctx, _ids, v_means2d, v_conics, v_opacities, v_features, _rect):  # noqa: ANN001, ANN205
        cot = _cotangents(ctx.ids.shape[0], ctx.arrays[0].dtype, v_means2d, v_conics, v_opacities, v_features)
        grads = _project_kernels.project_vjp(*(ctx.ids, *ctx.arrays, ctx.cam, ctx.lim, cot))
        return (*(torch.from_numpy(g).to(ctx.device) for g in grads), None, None, None)


class _Render(torch.autograd.Function):
    """Gaussian parameters → ``(feat [H, W, 4], trans [H, W], means2d [M, 2], ids [M], intersections)``: the fused
    projection, the tile binning and the compositing in one node; the backward reuses the forward's order and tile
    lists, sums the compositor's per-intersection rows per Gaussian and goes straight on into the projection's."""

    @staticmethod
    def forward(  # noqa: ANN205 - autograd signature
        ctx,  # noqa: ANN001
        means: torch.Tensor,
        log_scales: torch.Tensor,
        quats: torch.Tensor,
        opacity_logits: torch.Tensor,
        sh: torch.Tensor,
        cam: np.ndarray,
        lim: np.ndarray,
        size: tuple[int, int],
    ):
        w, h = size
        arrays = tuple(_np(t) for t in (means, log_scales, quats, opacity_logits, sh))
        ids, means2d, conics, opacities, features, rect = _project_kernels.project(*arrays + (cam, lim, w, h))
        offsets, lists, cap = _kernels.bin_tiles_lazy(rect, w, h, TILE_SIZE)
        splats = (means2d, conics, opacities, features, rect, offsets, lists, w, h, TILE_SIZE)
        feat, trans, last, short = _kernels.composite_forward(*splats, cap)
        if short:  # a tile's first `cap` Gaussians left pixels not done: its list is needed in full
            offsets, lists = _kernels.bin_tiles(rect, w, h, TILE_SIZE)
            splats, cap = splats[:5] + (offsets, lists) + splats[7:], 0
            feat, trans, last, _ = _kernels.composite_forward(*splats)
        ctx.arrays, ctx.cam, ctx.lim, ctx.ids, ctx.splats = arrays, cam, lim, ids, splats
        ctx.trans, ctx.last, ctx.device = trans, last, means.device
        outs = [torch.from_numpy(a).to(means.device) for a in (feat, trans, means2d, ids)]
        ctx.mark_non_differentiable(outs[3])
        return (*outs, lists.shape[0])

    @staticmethod
    @once_differentiable
    def backward(ctx, v_feat, v_trans, v_means2d, _ids, _n):  # noqa: ANN001, ANN205
        means2d, _, _, features, _, offsets, lists, w, h, _ = ctx.splats
        dtype, m = means2d.dtype, means2d.shape[0]
        v_feat = np.zeros((h, w, 4), dtype) if v_feat is None else _np(v_feat).astype(dtype, copy=False)
        v_trans = np.zeros((h, w), dtype) if v_trans is None else _np(v_trans).astype(dtype, copy=False)
        walked = np.empty(offsets.shape[0] - 1, np.int64)
        rows = _kernels.composite_backward(*ctx.splats + (ctx.trans, ctx.last, v_feat, v_trans, walked))
        cot = _workspace.zeros((m, _project_kernels.COT_COLS), dtype)
        _kernels.sum_rows(offsets, offsets[:-1] + walked, lists, rows, cot)  # the rows written, no more
        if v_means2d is not None:
            cot[:, :2] += _np(v_means2d)
        grads = _project_kernels.project_vjp(*(ctx.ids, *ctx.arrays, ctx.cam, ctx.lim, cot))
        return (*(torch.from_numpy(g).to(ctx.device) for g in grads), None, None, None)


def project_gaussians_fused(
    means: torch.Tensor,  # [N, 3]
    log_scales: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4]
    opacity_logits: torch.Tensor,  # [N]
    sh: torch.Tensor,  # [N, K, 3]
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """:func:`~.projection.project_gaussians` (same arguments and result) through the fused kernel; differentiable
    w.r.t. the five Gaussian parameters (the camera is a constant)."""
    cam, lim = _camera(viewmat, K, means.dtype, width, height, near, far, eps2d)
    ids, means2d, conics, opacities, features, rect = _Project.apply(
        means, log_scales, quats, opacity_logits, sh, cam, lim, (width, height)
    )
    return Projection(ids, means2d, conics, features[:, 3], opacities, features[:, :3], rect)


def render_fused(
    gaussians: Gaussians,
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """Project, bin and composite in one autograd node (``backend="numba"`` of :func:`~.rasterize.render`).

    Returns:
        ``(feat, trans, means2d, ids, intersections)``: the composited colour and depth ``Σ w (r, g, b, z)``
        [H, W, 4] (no background), the final transmittance [H, W], the kept Gaussians' pixel centres [M, 2]
        (differentiable) and indices [M] front to back, and the number of (tile, Gaussian) pairs.
    """
    cam, lim = _camera(viewmat, K, gaussians.dtype, width, height, near, far, eps2d)
    return _Render.apply(*gaussians.tensors(), cam, lim, (width, height))
