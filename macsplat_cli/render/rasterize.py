"""The public render function: Gaussians + one pinhole camera → RGB, depth, alpha."""

from __future__ import annotations

import logging
from typing import Literal

import torch

from .._checks import check_finite, check_shape
from .._limits import check_render_size
from ..cameras import Camera
from ..gaussians import Gaussians
from . import _gsplat, _workspace
from ._output import RenderOutput, normalise_depth
from .composite import bin_tiles, composite
from .fused import camera_needs_grad, render_fused
from .projection import Projection, project_gaussians
from .reference import composite_reference

__all__ = ["Backend", "RenderOutput", "render", "render_camera"]

logger = logging.getLogger(__name__)

Backend = Literal["auto", "numba", "torch", "gsplat"]
"""``numba``: compiled CPU kernels (default on CPU). ``torch``: the dense plain-PyTorch
twin, for tests and tiny images. ``gsplat``: CUDA through gsplat, if installed. ``auto``:
gsplat for CUDA tensors when available, else numba."""


def render(
    gaussians: Gaussians,
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    background: torch.Tensor | tuple[float, float, float] = (0.0, 0.0, 0.0),
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    backend: Backend = "auto",
) -> RenderOutput:
    """Render Gaussians into one camera (differentiable w.r.t. every Gaussian parameter).

    Args:
        gaussians: the scene (N Gaussians).
        viewmat: world-to-camera transform, OpenCV axes (x right, y down, z forward). [4, 4]
        K: intrinsics in pixels; pixel (i, j) has its centre at (j + 0.5, i + 0.5). [3, 3]
        width: image width in pixels.
        height: image height in pixels.
        background: colour behind the Gaussians, in [0, 1]. [3]
        near: Gaussians closer than this (camera z) are culled.
        far: Gaussians farther than this are culled.
        eps2d: low-pass dilation of the 2D covariances, px².
        backend: see :data:`Backend`.

    Returns:
        :class:`RenderOutput`. Non-finite Gaussians are culled, so the outputs are finite.

    Raises:
        ShapeError, NonFiniteError: a malformed or non-finite camera or background.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    viewmat, K, bg = _checked_camera(gaussians, viewmat, K, background)
    if backend == "gsplat" or (backend == "auto" and gaussians.device.type == "cuda"):
        if backend == "gsplat" or _gsplat.available():
            return _gsplat.render_gsplat(gaussians, viewmat, K, width, height, bg, near=near, far=far, eps2d=eps2d)
    _workspace.next_render()  # the CPU kernels' buffers: one more render (drops those idle for a few)
    if backend in ("numba", "auto") and not camera_needs_grad(viewmat, K):
        feat, trans, means2d, ids, n_isect = render_fused(
            gaussians, viewmat, K, width, height, near=near, far=far, eps2d=eps2d
        )
        return _output(feat, trans, bg, ids, means2d, n_isect)
    proj = project_gaussians(
        gaussians.means,
        gaussians.log_scales,
        gaussians.quats,
        gaussians.opacity_logits,
        gaussians.sh,
        viewmat,
        K,
        width,
        height,
        near=near,
        far=far,
        eps2d=eps2d,
    )
    features = torch.cat([proj.colors, proj.depths[:, None]], dim=-1)  # [M, 4]
    feat, trans, n_isect = _composite(proj, features, width, height, backend)
    return _output(feat, trans, bg, proj.ids, proj.means2d, n_isect)


def _output(
    feat: torch.Tensor, trans: torch.Tensor, bg: torch.Tensor, ids: torch.Tensor, means2d: torch.Tensor, n_isect: int
) -> RenderOutput:
    """The :class:`RenderOutput` of composited ``feat`` (r, g, b, z) [H, W, 4] and transmittance [H, W] over the
    background ``bg`` [3]."""
    alpha = 1.0 - trans
    rgb = feat[..., :3] + trans[..., None] * bg
    depth = normalise_depth(feat[..., 3], alpha)
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, visible=ids, means2d=means2d, n_intersections=n_isect)


def _checked_camera(
    gaussians: Gaussians, viewmat: torch.Tensor, K: torch.Tensor, background: torch.Tensor | tuple[float, float, float]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(viewmat [4, 4], K [3, 3], background [3])`` on the Gaussians' device and dtype, checked for shape and
    finiteness (ShapeError, NonFiniteError)."""
    dtype, device = gaussians.dtype, gaussians.device
    bg = torch.as_tensor(background, dtype=dtype, device=device).reshape(3)
    viewmat = torch.as_tensor(viewmat).to(device=device, dtype=dtype)
    K = torch.as_tensor(K).to(device=device, dtype=dtype)
    check_shape(viewmat, (4, 4), "viewmat")
    check_shape(K, (3, 3), "K")
    check_finite(viewmat, "viewmat")
    check_finite(K, "K")
    check_finite(bg, "background")
    return viewmat, K, bg


def _composite(
    proj: Projection, features: torch.Tensor, width: int, height: int, backend: Backend
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Alpha compositing of the projected Gaussians' ``features`` [M, C] on the CPU backends: ``(features [H, W, C],
    transmittance [H, W], tile intersections)`` (0 intersections for the dense ``torch`` twin)."""
    if backend == "torch":
        feat, trans = composite_reference(proj.means2d, proj.conics, proj.opacities, features, width, height)
        return feat, trans, 0
    if backend in ("numba", "auto"):
        tiles = bin_tiles(proj.pixel_rect, width, height)
        feat, trans = composite(
            proj.means2d, proj.conics, proj.opacities, features, proj.pixel_rect, width, height, tiles=tiles
        )
        return feat, trans, tiles.n_intersections
    raise ValueError(f"unknown render backend {backend!r}")


def render_camera(gaussians: Gaussians, camera: Camera, **kwargs: object) -> RenderOutput:
    """Render into a :class:`~macsplat_cli.cameras.Camera` (its size, K and pose).

    Keyword arguments are those of :func:`render`.

    Raises:
        InputError: the camera's image is larger than :data:`~macsplat_cli._limits.MAX_RENDER_SIDE` pixels
            on a side or :data:`~macsplat_cli._limits.MAX_RENDER_PIXELS` in all (checked before any
            framebuffer is allocated).
    """
    check_render_size(camera.width, camera.height)
    dev, dt = gaussians.device, gaussians.dtype
    viewmat = torch.tensor(camera.world_to_cam, dtype=dt, device=dev)
    K = torch.tensor(camera.K, dtype=dt, device=dev)
    return render(gaussians, viewmat, K, camera.width, camera.height, **kwargs)  # type: ignore[arg-type]
