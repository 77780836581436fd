"""Optional CUDA rendering through gsplat (Apache-2.0), imported lazily.

gsplat is never a dependency: it JIT-compiles CUDA code on first use and cannot run on a
CPU-only PyTorch. When it is installed and the Gaussians live on a CUDA device,
:func:`render_gsplat` calls ``gsplat.rasterization`` with the conventions of the CPU path
(OpenCV view matrix, pixel intrinsics, pixel centres at +0.5, 0.3 px² dilation, same near
plane). Differences that remain: gsplat clamps alpha at 0.999 (the CPU path at 0.99) and
bounds each splat by ``3.33·σ`` per axis before its own opacity-aware tightening.
"""

from __future__ import annotations

import importlib.util
from typing import TYPE_CHECKING

import torch

from ..errors import InputError
from ._output import RenderOutput, normalise_depth

if TYPE_CHECKING:
    from ..gaussians import Gaussians

__all__ = ["available", "render_gsplat"]


def available() -> bool:
    """True when gsplat is importable and a CUDA device is present."""
    return importlib.util.find_spec("gsplat") is not None and torch.cuda.is_available()


def _require_cuda(gaussians: Gaussians) -> None:
    if gaussians.device.type != "cuda":
        raise InputError("the gsplat backend renders CUDA tensors; move the Gaussians to a CUDA device")


def render_gsplat(
    gaussians: Gaussians,
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    background: torch.Tensor,  # [3]
    *,
    near: float,
    far: float,
    eps2d: float,
) -> RenderOutput:
    """Render with ``gsplat.rasterization``; same contract as :func:`~macsplat_cli.render.render`."""
    try:
        import gsplat
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise InputError("the gsplat backend needs gsplat and a CUDA PyTorch: pip install gsplat") from e
    _require_cuda(gaussians)

    keep = gaussians.finite_mask().nonzero().squeeze(1)  # gsplat would propagate NaN
    g = gaussians[keep]
    colors, alphas, meta = gsplat.rasterization(
        means=g.means,
        quats=g.quats,
        scales=g.scales,
        opacities=g.opacities,
        colors=g.sh,
        viewmats=viewmat[None],
        Ks=K[None],
        width=width,
        height=height,
        near_plane=near,
        far_plane=far,
        eps2d=eps2d,
        sh_degree=g.sh_degree,
        render_mode="RGB+D",
        packed=False,
    )
    alpha = alphas[0, ..., 0]
    rgb = colors[0, ..., :3] + (1.0 - alpha)[..., None] * background
    depth = normalise_depth(colors[0, ..., 3], alpha)
    radii = meta["radii"][0]
    visible_local = (radii > 0).reshape(radii.shape[0], -1).any(-1)
    return RenderOutput(
        rgb=rgb,
        depth=depth,
        alpha=alpha,
        visible=keep[visible_local],
        means2d=meta["means2d"][0][visible_local],
        n_intersections=int(meta.get("n_isects", 0) or 0),
    )
