"""Differentiable Gaussian rasterization: EWA projection, tile binning, alpha compositing.

The CPU path (default) uses compiled Numba kernels with a hand-written backward pass;
``reference.py`` is its plain-PyTorch twin. A CUDA path through gsplat is used when
gsplat is installed and the Gaussians live on a CUDA device.
"""

from __future__ import annotations

from ._kernels import compile_kernels
from .rasterize import Backend, RenderOutput, render, render_camera

__all__ = ["Backend", "RenderOutput", "compile_kernels", "render", "render_camera"]
