"""Random Gaussians in front of an identity camera, and a centred pinhole K to render them (render, PLY, CLI and stress
tests)."""

from __future__ import annotations

import torch

from macsplat_cli.gaussians import Gaussians


def random_gaussians(
    n: int,
    *,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    sh_degree: int = 0,
    extent: float = 1.0,
    z_range: tuple[float, float] = (2.0, 4.0),
    scale_range: tuple[float, float] = (0.02, 0.12),
    opacity_logit_range: tuple[float, float] = (-2.0, 2.0),
) -> Gaussians:
    """Random Gaussians in ``[-extent, extent]² × z_range`` in front of an identity camera."""
    g = torch.Generator().manual_seed(seed)

    def u(*shape: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64) * (hi - lo) + lo

    means = torch.stack(
        [u(n, lo=-extent, hi=extent), u(n, lo=-extent, hi=extent), u(n, lo=z_range[0], hi=z_range[1])], -1
    )
    log_scales = torch.log(u(n, 3, lo=scale_range[0], hi=scale_range[1]))
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacity = u(n, lo=opacity_logit_range[0], hi=opacity_logit_range[1])
    k = (sh_degree + 1) ** 2
    sh = torch.randn(n, k, 3, generator=g, dtype=torch.float64) * 0.5
    return Gaussians(means, log_scales, quats, opacity, sh).to(dtype)


def pinhole(width: int, height: int, focal: float | None = None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A centred pinhole K (principal point at the image centre). [3, 3]"""
    f = focal if focal is not None else float(width)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
