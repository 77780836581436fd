"""Residual Semantic Fusion: DINOv3 features add a learned residual to the matching descriptors.

MAC-Splat enriches the 24-d MASt3R matching descriptors ``f`` (final decoder output,
per pixel) with semantics from a frozen DINOv3 encoder:

1. ``p = proj(dino)``: a linear layer C → D on the DINOv3 patch grid [h, w];
2. ``p`` is resized bilinearly to the descriptor grid [H, W] (``align_corners=False``:
   pixel centres map to pixel centres, so a 16-px DINO patch centre lands at descriptor
   pixel ``16i + 7.5``). Projection and bilinear resizing are both linear and the
   resize weights sum to one, so this equals "resize the DINO features, then project";
   projecting first is cheaper (D = 24 channels are resized instead of C);
3. a per-pixel MLP (one MLP shared by every position) on ``[f, p]`` (2D channels):
   ``2D → hidden → … → D`` with GELU between layers, predicts ``r``;
4. ``f' = f + r``, then rescaled to the length of ``f`` (``renormalize=True``).

The last MLP layer is zero-initialised (weight and bias), so an untrained module gives
``r = 0`` exactly. Re-normalisation: MASt3R descriptors are L2-normalised and matched by
dot product/cosine, so ``f'`` must stay unit length for the matcher. Rather than
``(f + r) / ‖f + r‖`` (which moves a unit vector by an ulp even when ``r = 0``), ``f + r``
is rescaled by ``‖f‖ / ‖f + r‖``: unit descriptors stay unit (to rounding), and with
``r = 0`` the factor is exactly 1, so an untrained module returns the descriptors
bit-for-bit. Descriptors that are not unit length keep their length.

State dict (our own format, trained by us; ``depth`` = number of MLP linears, ≥ 2)::

    proj.weight      [D, C]        proj.bias      [D]
    layers.0.weight  [hidden, 2D]  layers.0.bias  [hidden]
    layers.i.weight  [hidden, hidden] (0 < i < depth-1)
    layers.{depth-1}.weight [D, hidden]  .bias [D]   # zero at initialisation

:func:`save_fusion` writes ``{"format", "version", "config", "state_dict"}`` to a ``.pth``
and :func:`load_fusion` reads it with ``torch.load(weights_only=True)``.

Shapes: ``B`` batch, ``H, W`` descriptor grid, ``D`` descriptor dim (24), ``h, w`` DINOv3
patch grid, ``C`` DINOv3 width.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from macsplat_cli._atomic import atomic_torch_save
from macsplat_cli._checks import check_shape
from macsplat_cli._state_dict import StateDictError, check_state_dict_keys, log_sha256
from macsplat_cli.errors import ShapeError
from macsplat_cli.neural.dinov3 import DINOv3Encoder

__all__ = [
    "FUSION_FORMAT",
    "FusionCheckpointError",
    "FusionConfig",
    "FusionResult",
    "ResidualSemanticFusion",
    "fuse_descriptors",
    "load_fusion",
    "save_fusion",
]

logger = logging.getLogger(__name__)

FUSION_FORMAT = "macsplat.residual_semantic_fusion"
_FUSION_VERSION = 1
MAX_FUSION_WIDTH = 8192
"""Widest descriptor, DINOv3 or hidden width a fusion config may have."""
MAX_FUSION_DEPTH = 64
"""Most linear layers in the fusion MLP."""


class FusionCheckpointError(StateDictError):
    """A fusion weight file is missing, unreadable, or does not match its config (``key``/``file_shape``/...)."""


@dataclass(frozen=True)
class FusionConfig:
    """Sizes of the Residual Semantic Fusion module.

    Args:
        desc_dim: descriptor dimension D (24 for MASt3R's ``desc24``).
        dino_dim: DINOv3 feature width C (384 for ViT-S/S+, 768 B, 1024 L); the default
            is ViT-S/16, the cheapest encoder on a CPU. Use ``encoder.config.embed_dim``.
        hidden_dim: width of the MLP's hidden layers.
        depth: number of linear layers in the MLP (2: ``2D → hidden → D``).
        renormalize: rescale ``f + r`` to the length of ``f`` (keeps unit descriptors unit).
    """

    desc_dim: int = 24
    dino_dim: int = 384
    hidden_dim: int = 64
    depth: int = 2
    renormalize: bool = True

    def __post_init__(self) -> None:
        sizes = {k: getattr(self, k) for k in ("desc_dim", "dino_dim", "hidden_dim", "depth")}
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in sizes.values()):
            raise ValueError(f"FusionConfig sizes must be whole numbers: {self}")
        if min(self.desc_dim, self.dino_dim, self.hidden_dim) <= 0:
            raise ValueError(f"FusionConfig sizes must be positive: {self}")
        if self.depth < 2:
            raise ValueError(f"FusionConfig.depth must be at least 2 (input and output layers), got {self.depth}")
        # Bounds: the config of a fusion file is untrusted and sizes the module before its weights are checked.
        for key, most in (("desc_dim", MAX_FUSION_WIDTH), ("dino_dim", MAX_FUSION_WIDTH),
                          ("hidden_dim", MAX_FUSION_WIDTH), ("depth", MAX_FUSION_DEPTH)):  # fmt: skip
            if sizes[key] > most:
                raise ValueError(f"FusionConfig.{key}={sizes[key]} is out of range (at most {most})")


class ResidualSemanticFusion(nn.Module):
    """Per-pixel residual MLP on ``[descriptor, projected DINOv3 feature]``; identity when untrained.

    See the module docstring for the maths, the re-normalisation and the state-dict keys.
    """

    def __init__(self, config: FusionConfig | None = None) -> None:
        super().__init__()
        self.config = config or FusionConfig()
        cfg = self.config
        self.proj = nn.Linear(cfg.dino_dim, cfg.desc_dim)
        widths = [2 * cfg.desc_dim] + [cfg.hidden_dim] * (cfg.depth - 1) + [cfg.desc_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        last = self.layers[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def project_dino(self, dino: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """Project DINOv3 features to D channels and resize them bilinearly to the descriptor grid.

        Args:
            dino: [B, h, w, C]
            size: the descriptor grid ``(H, W)``.

        Returns:
            [B, H, W, D]
        """
        p = self.proj(dino)  # [B, h, w, D]
        if tuple(p.shape[1:3]) == tuple(size):
            return p
        p = F.interpolate(p.permute(0, 3, 1, 2), size=size, mode="bilinear", align_corners=False)
        return p.permute(0, 2, 3, 1)

    def residual(self, desc: torch.Tensor, dino: torch.Tensor) -> torch.Tensor:
        """The residual ``r`` the MLP predicts. desc [B, H, W, D], dino [B, h, w, C] → [B, H, W, D]"""
        z = torch.cat([desc, self.project_dino(dino, (desc.shape[1], desc.shape[2]))], dim=-1)  # [B, H, W, 2D]
        for layer in self.layers[:-1]:
            z = F.gelu(layer(z))
        return self.layers[-1](z)

    def forward(self, desc: torch.Tensor, dino: torch.Tensor) -> torch.Tensor:
        """Fused descriptors ``f' = (f + r)·‖f‖/‖f + r‖`` (or ``f + r`` without ``renormalize``).

        Args:
            desc: matching descriptors. [B, H, W, D]
            dino: DINOv3 patch features (any grid; resized to [H, W]). [B, h, w, C]

        Returns:
            [B, H, W, D]; exactly ``desc`` while the last layer is zero (untrained).

        Raises:
            ShapeError: wrong dims, or batch sizes that differ.
        """
        cfg = self.config
        check_shape(desc, ("B", "H", "W", cfg.desc_dim), "descriptors")
        check_shape(dino, (desc.shape[0], "h", "w", cfg.dino_dim), "DINOv3 features")
        out = desc + self.residual(desc, dino.to(desc.dtype))
        if not cfg.renormalize:
            return out
        n_in = torch.linalg.vector_norm(desc, dim=-1, keepdim=True)
        n_out = torch.linalg.vector_norm(out, dim=-1, keepdim=True)
        tiny = torch.finfo(out.dtype).tiny
        scale = torch.where(n_out > 0, n_in / n_out.clamp_min(tiny), torch.ones_like(n_out))
        return out * scale


@dataclass(frozen=True)
class FusionResult:
    """Outcome of :func:`fuse_descriptors`.

    Attributes:
        desc: the fused descriptors, or the input unchanged when skipped. [B, H, W, D]
        applied: whether the fusion ran.
        report: one line for the run report saying what was done.
    """

    desc: torch.Tensor
    applied: bool
    report: str


def fuse_descriptors(
    desc: torch.Tensor,
    image: torch.Tensor,
    *,
    fusion: ResidualSemanticFusion | None,
    encoder: DINOv3Encoder | None,
) -> FusionResult:
    """Apply Residual Semantic Fusion when a DINOv3 encoder is available; otherwise skip it.

    The encoder runs under ``torch.no_grad()`` (it is frozen: gradients reach the fusion
    parameters and the descriptors, never the encoder).

    Args:
        desc: matching descriptors (final decoder output). [B, H, W, D]
        image: the images the descriptors come from, macsplat convention, in [-1, 1];
            sides multiples of 16. [B, 3, H_img, W_img]
        fusion: the trained fusion module; None skips the fusion.
        encoder: the frozen DINOv3 encoder; None (no weights given) skips the fusion.

    Returns:
        :class:`FusionResult`; when skipped, ``desc`` is the input tensor itself.

    Raises:
        ShapeError: batch sizes differ, or the widths do not match the fusion config.
    """
    if encoder is None or fusion is None:
        missing = "no DINOv3 encoder (weights not given)" if encoder is None else "no fusion weights"
        report = f"semantic fusion skipped: {missing}; descriptors unchanged"
        logger.debug("%s", report)
        return FusionResult(desc=desc, applied=False, report=report)
    if encoder.config.embed_dim != fusion.config.dino_dim:
        raise ShapeError(
            "DINOv3 features", (encoder.config.embed_dim,), f"width {fusion.config.dino_dim} (FusionConfig.dino_dim)"
        )
    check_shape(image, (desc.shape[0], 3, "H", "W"), "image")
    with torch.no_grad():
        dino = encoder(image)  # [B, h, w, C]
    out = fusion(desc, dino)
    b, h, w, c = dino.shape
    report = (
        f"semantic fusion applied: DINOv3 {encoder.config.name} features {h}×{w}×{c} → "
        f"descriptors {desc.shape[1]}×{desc.shape[2]}×{desc.shape[3]}"
    )
    logger.debug("%s", report)
    return FusionResult(desc=out, applied=True, report=report)


def save_fusion(module: ResidualSemanticFusion, path: str | os.PathLike[str]) -> Path:
    """Write ``{"format", "version", "config", "state_dict"}`` to ``path`` atomically; returns the path."""
    payload = {
        "format": FUSION_FORMAT,
        "version": _FUSION_VERSION,
        "config": dataclasses.asdict(module.config),
        "state_dict": {k: v.detach().cpu() for k, v in module.state_dict().items()},
    }
    return atomic_torch_save(path, payload)


def load_fusion(path: str | os.PathLike[str], *, device: torch.device | str = "cpu") -> ResidualSemanticFusion:
    """Read a file written by :func:`save_fusion` (``torch.load(weights_only=True)``, strict keys).

    Raises:
        FusionCheckpointError: missing or unreadable file, another format, or keys/shapes
            that do not match the stored config (the first bad key is named).
    """
    p = Path(path)
    if not p.is_file():
        raise FusionCheckpointError(f"fusion weights not found: {p} (train them or omit the fusion step)")
    log_sha256(p, logger, "fusion weights")
    try:
        obj = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load's exception types are unspecified (IndexError on some garbage)
        raise FusionCheckpointError(f"{p}: not a readable PyTorch file: {type(e).__name__}: {e}") from e
    if not isinstance(obj, Mapping) or obj.get("format") != FUSION_FORMAT:
        raise FusionCheckpointError(f"{p}: not a macsplat fusion file (expected format {FUSION_FORMAT!r})")
    if obj.get("version") != _FUSION_VERSION:
        raise FusionCheckpointError(f"{p}: fusion file version {obj.get('version')!r}, expected {_FUSION_VERSION}")
    try:
        cfg = FusionConfig(**obj["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise FusionCheckpointError(f"{p}: bad fusion config: {e}") from None
    state = obj.get("state_dict")
    if not isinstance(state, Mapping):
        raise FusionCheckpointError(f"{p}: no state_dict")
    with torch.device("meta"):  # sized by the file's config: check the weights before allocating anything
        module = ResidualSemanticFusion(cfg)
    expected = {k: v.shape for k, v in module.state_dict().items()}
    check_state_dict_keys(expected, state, FusionCheckpointError, source=str(p), model="the fusion module")
    module.to_empty(device="cpu")
    module.load_state_dict(state, strict=True)
    return module.to(device)
