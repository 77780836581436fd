"""Compositing constants shared by the Numba kernels, the PyTorch twin and the projection.

They are rounded to float32 once, so that the float32 and float64 paths use
bit-identical thresholds.
"""

from __future__ import annotations

import numpy as np

ALPHA_MIN = float(np.float32(1.0 / 255.0))
"""Samples with a smaller alpha are skipped; Gaussians that cannot reach it are culled."""
ALPHA_MAX = float(np.float32(0.99))
"""Alpha is clamped to this, so that ``1 − alpha ≥ 0.01`` in the backward division."""
T_MIN = float(np.float32(1e-4))
"""A pixel stops before the sample that would bring its transmittance to this or below."""
