"""Differentiable Gaussian rasterization: EWA projection, tile binning, alpha compositing.

The CPU path (default) uses compiled Numba kernels with a hand-written backward pass (the
projection in ``fused.py``, the compositing in ``composite.py``); ``projection.py`` and
``reference.py`` are their plain-PyTorch twins. A CUDA path through gsplat is used when
gsplat is installed and the Gaussians live on a CUDA device.
"""

from __future__ import annotations

from . import _kernels, _project_kernels
from .rasterize import Backend, RenderOutput, render, render_camera

__all__ = ["Backend", "RenderOutput", "compile_kernels", "render", "render_camera"]


def compile_kernels() -> None:
    """Compile (or load from Numba's cache) the CPU kernels a forward render needs, in the order it needs them,
    without running them (for a background thread)."""
    _project_kernels.compile_kernels()
    _kernels.compile_kernels()
