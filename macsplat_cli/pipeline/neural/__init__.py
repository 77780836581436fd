"""The neural backend in the pipeline's stage slots (``--backend neural``).

* :mod:`.pair`: the ``pair`` stage (the :class:`~macsplat_cli.neural.predictor.PairPredictor`'s one pass
  per pair) and the neural stages' settings;
* :mod:`.stages`: the descriptor, pose, depth and Gaussian stages that read its output;
* :mod:`.geometry`: focal length (Weiszfeld) from point maps, descriptor sampling (the pose from the point map,
  PnP, is in :mod:`..pose.pnp`);
* :mod:`.warp`: a view's working pixels ↔ the network grid.
"""

from __future__ import annotations

from .geometry import estimate_focal_weiszfeld, pixel_grid, sample_descriptors
from .pair import NetworkPair, NeuralConfig, NeuralPair
from .stages import (
    NeuralDepth,
    NeuralDescriptors,
    NeuralGaussians,
    NeuralPose,
    network_pass,
    neural_stages,
    refine_matches,
)  # fmt: skip
from .warp import ViewWarp

__all__ = [
    "NetworkPair",
    "NeuralConfig",
    "NeuralDepth",
    "NeuralDescriptors",
    "NeuralGaussians",
    "NeuralPair",
    "NeuralPose",
    "ViewWarp",
    "estimate_focal_weiszfeld",
    "network_pass",
    "neural_stages",
    "pixel_grid",
    "refine_matches",
    "sample_descriptors",
]
