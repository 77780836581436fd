"""The :class:`~.predictor.PairPredictor` from the user's files: official checkpoints (MASt3R, Splatt3R, DINOv3)
with macsplat fusion weights, or one macsplat predictor checkpoint (:mod:`.predictor_io`).

The files are checked against each other before any work: a Splatt3R head sized by the MASt3R backbone it
joins, fusion weights that fit the DINOv3 encoder and the backbone's descriptors.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..errors import InputError
from .checkpoints import CheckpointNotFoundError, load_mast3r
from .dinov3 import load_dinov3
from .fusion import load_fusion
from .gaussian_head import GaussianHead
from .predictor import MISSING_WEIGHTS_HELP, PairPredictor, check_fusion_files
from .predictor_io import is_predictor_checkpoint, load_predictor_checkpoint
from .splatt3r import load_splatt3r

__all__ = ["load_pair_predictor"]

logger = logging.getLogger(__name__)


def load_pair_predictor(
    *,
    weights: Path | str | None = None,
    gaussian_head: Path | str | None = None,
    dino: Path | str | None = None,
    fusion: Path | str | None = None,
) -> PairPredictor:
    """The predictor from the user's checkpoints, on the CPU in eval mode (move it with ``.to(device)``).

    * ``weights`` (MASt3R ``.pth`` or Hugging Face folder): the backbone; or a macsplat checkpoint
      (``macsplat train``'s ``.pt``, :mod:`.predictor_io`), which holds the whole predictor.
    * ``gaussian_head`` (Splatt3R ``.ckpt``): the Gaussian head. A Splatt3R checkpoint holds its
      frozen MASt3R too, so it alone is enough; with ``weights`` as well, the backbone comes from
      ``weights`` (its architecture, from its ``args``, also sizes the head) and only the head is taken
      from the Splatt3R file (Splatt3R trained its head on the released MASt3R weights, frozen).
    * ``dino`` and ``fusion`` go together: semantic fusion needs both the DINOv3 encoder and the
      trained fusion weights.

    Raises:
        CheckpointNotFoundError: neither ``weights`` nor ``gaussian_head`` (the message says which
            file is needed and where to get it), or a file that does not exist.
        CheckpointError / DINOv3CheckpointError / FusionCheckpointError: a file that does not fit.
        InputError: ``dino`` without ``fusion`` (or the reverse), widths that do not match.
    """
    if weights is None and gaussian_head is None:
        raise CheckpointNotFoundError(MISSING_WEIGHTS_HELP)
    check_fusion_files(dino, fusion)
    if weights is not None and is_predictor_checkpoint(weights):
        others = [flag for flag, v in (("--gaussian-head", gaussian_head), ("--dino", dino), ("--fusion", fusion)) if v]
        if others:
            raise InputError(
                f"{weights} is a macsplat checkpoint: it carries its own Gaussian head, DINOv3 and fusion weights; "
                f"drop {', '.join(others)}"
            )
        predictor, meta = load_predictor_checkpoint(weights)
        logger.info(
            "macsplat checkpoint %s (%s)", weights, ", ".join(f"{k} {v}" for k, v in meta.items() if k == "step")
        )
        return predictor
    head: GaussianHead | None = None
    if weights is not None:
        backbone, _ = load_mast3r(weights)
        if gaussian_head is not None:
            _, head, _ = load_splatt3r(
                gaussian_head, backbone_config=backbone.config.replace(head_type="gaussian_head")
            )
    else:
        assert gaussian_head is not None
        backbone, head, _ = load_splatt3r(gaussian_head)
    encoder = fusion_module = None
    if dino is not None and fusion is not None:
        encoder, fusion_module = load_dinov3(dino), load_fusion(fusion)
        try:
            predictor = PairPredictor(backbone, head, encoder, fusion_module)
        except InputError as e:
            raise InputError(f"{fusion} does not fit {dino} and the backbone: {e}") from None
    else:
        predictor = PairPredictor(backbone, head)
    logger.info(
        "neural backend: MASt3R %.0fM parameters%s%s",
        sum(p.numel() for p in backbone.parameters()) / 1e6,
        ", Splatt3R Gaussian head" if head is not None else "",
        f", DINOv3 {encoder.config.name} fusion" if encoder is not None else "",
    )
    return predictor.eval()
