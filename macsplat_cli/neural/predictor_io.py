"""macsplat predictor checkpoints: a whole :class:`~.predictor.PairPredictor` (backbone, Gaussian head, DINOv3,
fusion) with the configuration that rebuilds it, in one ``.pt`` file that ``torch.load(weights_only=True)`` reads.

``macsplat train`` writes them; ``--weights FILE.pt`` of ``reconstruct``/``eval``/``bench --backend neural``
(and ``export-onnx``) reads them as they are. Layout::

    {"format": "macsplat-predictor", "version": 1,
     "config": {"backbone": {...}, "gaussian_head": {...} | None, "dino": {...} | None, "fusion": {...} | None},
     "state_dict": {...},            # PairPredictor.state_dict()
     "meta": {...}}                  # free-form: training step, metrics, source files (plain values)

Configurations are plain dicts of the config dataclasses' fields (tuples, floats, strings), so the file
holds no pickled class.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any

import torch

from .._atomic import atomic_torch_save
from .._state_dict import StateDictError, check_state_dict_keys, log_sha256
from ..errors import InputError
from .backbone import MASt3RBackbone
from .config import BackboneConfig, GaussianHeadConfig
from .dinov3 import DINOv3Config, DINOv3Encoder
from .fusion import FusionConfig, ResidualSemanticFusion
from .gaussian_head import GaussianHead
from .predictor import PairPredictor

__all__ = [
    "PREDICTOR_FORMAT",
    "PredictorCheckpointError",
    "build_predictor",
    "is_predictor_checkpoint",
    "load_predictor_checkpoint",
    "predictor_config",
    "save_predictor_checkpoint",
]

logger = logging.getLogger(__name__)

PREDICTOR_FORMAT = "macsplat-predictor"
_VERSION = 1


class PredictorCheckpointError(StateDictError):
    """A macsplat predictor checkpoint that is unreadable or does not fit its own configuration."""


def predictor_config(predictor: PairPredictor) -> dict[str, dict[str, Any] | None]:
    """The configuration that rebuilds ``predictor`` (plain dicts)."""

    def plain(cfg: Any) -> dict[str, Any] | None:
        return None if cfg is None else dataclasses.asdict(cfg)

    return {
        "backbone": plain(predictor.backbone.config),
        "gaussian_head": plain(predictor.gaussian_head.config) if predictor.gaussian_head is not None else None,
        "dino": plain(predictor.dino.config) if predictor.dino is not None else None,
        "fusion": plain(predictor.fusion.config) if predictor.fusion is not None else None,
    }


def _as_config(cls: type, fields: dict[str, Any]) -> Any:
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(fields) - names)
    if unknown:
        raise InputError(f"unknown {cls.__name__} field {unknown[0]!r}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})


def build_predictor(config: dict[str, dict[str, Any] | None]) -> PairPredictor:
    """A predictor with freshly initialised weights from a :func:`predictor_config` dict."""
    backbone_cfg = _as_config(BackboneConfig, config["backbone"] or {})
    backbone = MASt3RBackbone(backbone_cfg)
    head = None
    if (head_fields := config.get("gaussian_head")) is not None:
        head_cfg = _as_config(GaussianHeadConfig, head_fields)
        head = GaussianHead(backbone_cfg.replace(head_type="gaussian_head"), head_cfg)
    dino = fusion = None
    if (dino_fields := config.get("dino")) is not None and (fusion_fields := config.get("fusion")) is not None:
        dino = DINOv3Encoder(_as_config(DINOv3Config, dino_fields))
        fusion = ResidualSemanticFusion(_as_config(FusionConfig, fusion_fields))
    return PairPredictor(backbone, head, dino, fusion)


def save_predictor_checkpoint(
    path: str | os.PathLike[str], predictor: PairPredictor, meta: dict[str, Any] | None = None
) -> Path:
    """Write ``predictor`` (weights on the CPU) and its configuration to ``path`` atomically."""
    payload = {
        "format": PREDICTOR_FORMAT,
        "version": _VERSION,
        "config": predictor_config(predictor),
        "state_dict": {k: v.detach().cpu() for k, v in predictor.state_dict().items()},
        "meta": dict(meta or {}),
    }
    return atomic_torch_save(path, payload)


def _read(path: Path) -> Any:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, OSError, EOFError, ValueError) as e:
        raise PredictorCheckpointError(f"{path}: not a readable checkpoint ({str(e).splitlines()[0]})") from None


def is_predictor_checkpoint(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a file holding a macsplat predictor checkpoint (not a MASt3R/Splatt3R one)."""
    p = Path(path)
    if not p.is_file() or p.suffix.lower() not in (".pt", ".pth"):
        return False
    try:
        obj = torch.load(p, map_location="meta", weights_only=True)
    except Exception:  # noqa: BLE001 - anything unreadable is simply not ours; the real loader reports it
        return False
    return isinstance(obj, dict) and obj.get("format") == PREDICTOR_FORMAT


def load_predictor_checkpoint(path: str | os.PathLike[str]) -> tuple[PairPredictor, dict[str, Any]]:
    """The predictor of a macsplat checkpoint (CPU, eval mode) and its ``meta``.

    Raises:
        PredictorCheckpointError: not a macsplat predictor checkpoint, a newer version, or weights that do
            not fit the stored configuration (the first bad key named with both shapes).
    """
    p = Path(path)
    if not p.is_file():
        raise PredictorCheckpointError(f"macsplat checkpoint not found: {p}")
    obj = _read(p)
    if not isinstance(obj, dict) or obj.get("format") != PREDICTOR_FORMAT:
        raise PredictorCheckpointError(f"{p}: not a macsplat predictor checkpoint (no format {PREDICTOR_FORMAT!r})")
    if int(obj.get("version", 0)) > _VERSION:
        raise PredictorCheckpointError(f"{p}: checkpoint version {obj['version']} is newer than this macsplat reads")
    try:
        predictor = build_predictor(obj["config"])
    except (KeyError, TypeError, InputError) as e:
        raise PredictorCheckpointError(f"{p}: its configuration does not describe a predictor ({e})") from None
    state = obj.get("state_dict")
    if not isinstance(state, dict):
        raise PredictorCheckpointError(f"{p}: no state_dict")
    expected = {k: tuple(v.shape) for k, v in predictor.state_dict().items()}
    check_state_dict_keys(expected, state, PredictorCheckpointError, source=str(p), model="the predictor")
    predictor.load_state_dict(state, strict=True)
    log_sha256(p, logger, "macsplat checkpoint")
    return predictor.eval(), dict(obj.get("meta") or {})
