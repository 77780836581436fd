"""The model ``macsplat train`` optimises: a :class:`~macsplat_cli.neural.predictor.PairPredictor` with a Gaussian
head and Residual Semantic Fusion, built from the user's checkpoints or at random, and which parts are frozen.

* ``--model full``: the released architectures (MASt3R ViT-L/ViT-B, Splatt3R head, DINOv3 + fusion: ViT-L/16 by
  default, the variant the MAC-Splat authors used);
  with ``--init random`` they start from random weights (no download), else from ``--weights`` (MASt3R),
  ``--gaussian-head`` (Splatt3R), ``--dino`` (DINOv3), and optionally ``--checkpoint`` (a macsplat checkpoint
  to continue from);
* ``--model tiny``: a small ViT (2 encoder, 3 decoder blocks, 64/32 wide; tiny DINOv3) that trains in minutes
  on a CPU without any weights, for trying the whole loop.

Trainable: the Gaussian head and the fusion module; the MASt3R backbone and DINOv3 are frozen (as in the paper)
unless ``train_backbone`` (DINOv3 is always frozen).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import torch

from ..errors import InputError
from ..neural.backbone import MASt3RBackbone
from ..neural.config import BackboneConfig, GaussianHeadConfig
from ..neural.dinov3 import DINOv3Config, DINOv3Encoder
from ..neural.fusion import FusionConfig, ResidualSemanticFusion
from ..neural.gaussian_head import GaussianHead
from ..neural.predictor import PairPredictor

__all__ = [
    "INITS",
    "MODELS",
    "Init",
    "ModelKind",
    "ModelSpec",
    "build_training_model",
    "freeze_for_training",
    "trainable_parameters",
]

logger = logging.getLogger(__name__)


ModelKind = Literal["tiny", "full"]
"""``--model``: the architecture of a random init."""
Init = Literal["weights", "random"]
"""``--init``: start from checkpoints, or at random."""
MODELS: tuple[ModelKind, ...] = get_args(ModelKind)
INITS: tuple[Init, ...] = get_args(Init)


@dataclass
class ModelSpec:
    """Where the trained model comes from.

    Args:
        model: ``"tiny"`` or ``"full"`` (architecture of a random init).
        init: ``"random"``, or ``"weights"`` (the files below).
        weights: MASt3R checkpoint, or a macsplat checkpoint (the whole predictor, e.g. to fine-tune further).
        gaussian_head: Splatt3R checkpoint (its head; alone it also gives the backbone).
        dino: DINOv3 weights (with ``init="weights"``; a fresh fusion module is added on top).
        no_dino: build no DINOv3/fusion at all (the "w/o DINO" ablation).
        seed: seed of the random initialisation.
        dino_variant: DINOv3 preset of ``model="full"`` at random (with ``dino``, the file's variant).
        max_scale: cap of the Gaussian head's scales (:class:`~macsplat_cli.neural.config.GaussianHeadConfig`);
            None keeps a loaded macsplat checkpoint's cap (a fresh head: none).
    """

    model: ModelKind = "tiny"
    init: Init = "random"
    weights: Path | None = None
    gaussian_head: Path | None = None
    dino: Path | None = None
    no_dino: bool = False
    seed: int = 0
    dino_variant: str = "vitl16"
    max_scale: float | None = None


def _random(spec: ModelSpec) -> PairPredictor:
    if spec.model == "tiny":
        backbone_cfg = BackboneConfig.tiny()
        dino_cfg = DINOv3Config.preset("tiny")
    elif spec.model == "full":
        backbone_cfg = BackboneConfig()
        try:
            dino_cfg = DINOv3Config.preset(spec.dino_variant)
        except ValueError as e:
            raise InputError(str(e)) from None
    else:
        raise InputError(f"--model {spec.model!r}: use tiny or full")
    backbone = MASt3RBackbone(backbone_cfg)
    head = GaussianHead(backbone_cfg.replace(head_type="gaussian_head"), GaussianHeadConfig(max_scale=spec.max_scale))
    if spec.no_dino:
        return PairPredictor(backbone, head)
    fusion = ResidualSemanticFusion(FusionConfig(desc_dim=backbone_cfg.local_feat_dim, dino_dim=dino_cfg.embed_dim))
    return PairPredictor(backbone, head, DINOv3Encoder(dino_cfg), fusion)


def build_training_model(spec: ModelSpec) -> PairPredictor:
    """The predictor to train (CPU; call :func:`freeze_for_training` next).

    Raises:
        InputError: an unknown model, weights missing for ``init="weights"``, files that do not fit.
    """
    if spec.init == "random":
        if any(v is not None for v in (spec.weights, spec.gaussian_head, spec.dino)):
            raise InputError("--init random builds the model from scratch: drop --weights, --gaussian-head and --dino")
        torch.manual_seed(spec.seed)
        predictor = _random(spec)
        logger.info("model %s, random initialisation (seed %d)", spec.model, spec.seed)
        return predictor
    if spec.init != "weights":
        raise InputError(f"--init {spec.init!r}: use random or weights")
    from ..neural.loading import load_pair_predictor
    from ..neural.predictor_io import is_predictor_checkpoint

    if spec.weights is not None and is_predictor_checkpoint(spec.weights):
        predictor = load_pair_predictor(weights=spec.weights)
    else:
        predictor = load_pair_predictor(weights=spec.weights, gaussian_head=spec.gaussian_head)
        if predictor.gaussian_head is None:  # MASt3R alone: a fresh Splatt3R-style head to train
            cfg = predictor.backbone.config
            torch.manual_seed(spec.seed)
            predictor.gaussian_head = GaussianHead(cfg.replace(head_type="gaussian_head"), GaussianHeadConfig())
        if spec.dino is not None and not spec.no_dino:
            from ..neural.dinov3 import load_dinov3

            dino = load_dinov3(spec.dino)
            torch.manual_seed(spec.seed)
            fusion = ResidualSemanticFusion(
                FusionConfig(desc_dim=predictor.backbone.config.local_feat_dim, dino_dim=dino.config.embed_dim)
            )
            predictor = PairPredictor(predictor.backbone, predictor.gaussian_head, dino, fusion)
    if spec.no_dino and predictor.fusion_enabled:
        predictor = PairPredictor(predictor.backbone, predictor.gaussian_head)
    head = predictor.gaussian_head
    if head is not None and spec.max_scale is not None:
        head.config = dataclasses.replace(head.config, max_scale=spec.max_scale)
    elif head is not None and head.config.max_scale is not None:
        logger.info("the Gaussian head keeps its checkpoint's scale cap %g", head.config.max_scale)
    return predictor


def freeze_for_training(predictor: PairPredictor, *, train_backbone: bool = False) -> PairPredictor:
    """Gaussian head and fusion trainable; backbone frozen unless ``train_backbone``; DINOv3 always frozen.

    Frozen modules stay in eval mode during training (no dropout or batch statistics change).
    """
    for p in predictor.parameters():
        p.requires_grad_(False)
    trainable = [predictor.gaussian_head, predictor.fusion] + ([predictor.backbone] if train_backbone else [])
    for module in trainable:
        if module is not None:
            for p in module.parameters():
                p.requires_grad_(True)
    return predictor


def trainable_parameters(predictor: PairPredictor) -> list[torch.nn.Parameter]:
    return [p for p in predictor.parameters() if p.requires_grad]
