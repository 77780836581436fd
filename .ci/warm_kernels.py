"""CI only: compile the stages' Numba kernels into Numba's on-disk cache (``cache=True``: ``__pycache__`` beside the
kernels, in this checkout) while mypy runs on the other core, so that the test processes load them instead of each
compiling the ones it needs: the forward kernels the stages warm themselves (``compile_kernels``), and the
rasterizer's backward and float64 kernels (its twin tests and gradchecks), which compile when first used (~25 CPU-s
more into an empty cache)."""

import torch

from macsplat_cli import render
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.pipeline import depth, matching

matching.compile_kernels()
depth.compile_kernels()
render.compile_kernels()
for dtype in (torch.float32, torch.float64):
    one = Gaussians(
        torch.tensor([[0.0, 0.0, 2.0]], dtype=dtype), torch.full((1, 3), -2.0, dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype), torch.zeros(1, dtype=dtype),
        torch.zeros(1, 4, 3, dtype=dtype),
    )  # fmt: skip
    leaves = [one.means, one.log_scales, one.quats, one.opacity_logits, one.sh]
    for t in leaves:
        t.requires_grad_(True)
    K = torch.tensor([[16.0, 0.0, 8.0], [0.0, 16.0, 8.0], [0.0, 0.0, 1.0]], dtype=dtype)
    out = render.render(one, torch.eye(4, dtype=dtype), K, 16, 16, backend="numba")
    torch.autograd.grad(out.rgb.sum() + out.depth.sum() + out.alpha.sum(), leaves)
