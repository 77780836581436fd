"""Training of the pair predictor (``macsplat train``): the data (:mod:`.data`), the model, the objective; the
settings (:mod:`.config`, named by :mod:`.recipes`) and the entry point (:func:`train`, :mod:`.runner`)."""

from .config import TrainConfig
from .runner import TrainOutcome, TrainProgress, TrainSpec, train

__all__ = ["TrainConfig", "TrainOutcome", "TrainProgress", "TrainSpec", "train"]
