"""Differentiable Gaussian rasterization: EWA projection, tile binning, alpha compositing.

The CPU path (default) uses compiled Numba kernels with a hand-written backward pass (the
projection in ``fused.py``, the compositing in ``composite.py``); ``projection.py`` and
``reference.py`` are their plain-PyTorch twins. A CUDA path through gsplat is used when
gsplat is installed and the Gaussians live on a CUDA device.
"""

from __future__ import annotations

from . import _kernels, _project_kernels
from .rasterize import Backend, RenderOutput, render, render_camera

__all__ = ["Backend", "RenderOutput", "compile_kernels", "kernels_uncached", "render", "render_camera"]


def compile_kernels() -> None:
    """Compile (or load from Numba's cache) the CPU kernels a forward render needs, in the order it needs them,
    without running them (for a background thread)."""
    _project_kernels.compile_kernels()
    _kernels.compile_kernels()


def kernels_uncached() -> bool:
    """Whether Numba's cache holds no compiled projection kernel for these sources (a first run: the forward
    render's kernels will compile). False when it holds one, or when Numba's cache is not laid out as expected."""
    try:
        cache = _project_kernels.project_range._cache  # type: ignore[attr-defined]  # Numba's, for its own index
        return not cache._cache_file._load_index()
    except Exception:  # noqa: BLE001 - Numba's internals moved: assume cached (nothing is started for it)
        return False
