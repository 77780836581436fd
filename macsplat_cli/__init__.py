"""macsplat: two photos in, a 3D Gaussian splat scene out (the MAC-Splat method).

Symbols used in shapes across the package: ``N`` Gaussians, ``M`` visible Gaussians or
matches, ``K`` SH coefficients per channel, ``C`` channels, ``H``/``W`` image height and
width, ``V`` views, ``D`` descriptor dimension.
"""

from __future__ import annotations

import os as _os
import sys as _sys

# Numba's and PyTorch's OpenMP pools share the CPU cores. With the default (active)
# wait policy, idle threads of one pool spin for up to hundreds of milliseconds and
# starve the other: measured 40 ms → 2 s for a projection step on 2 cores. OpenMP reads
# this once, when torch loads, so it is set (as a default) before torch is imported.
if "torch" not in _sys.modules:
    _os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"

__all__ = ["__version__"]
