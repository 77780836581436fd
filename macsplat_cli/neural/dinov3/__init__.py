"""The frozen DINOv3 ViT encoder that gives MAC-Splat its semantic features.

A clean-room implementation written from the description in the project's reference
notes (DINOv3 code is under the custom "DINOv3 License", so no upstream source is used).
Attribute names mirror the keys of the official checkpoints, so an official ``.pth``
loads with ``strict=True``; the Hugging Face layout is mapped onto the same names.

Architecture (all released ViTs): 16-px patch embedding (a strided conv), one CLS token
and 4 register ("storage") tokens, pre-norm blocks ``x + ls1(attn(norm1 x))``,
``x + ls2(ffn(norm2 x))`` with LayerScale, a GELU MLP (S, B, L) or a SwiGLU FFN
(S+, L+, H+: ``w3(silu(w1 x) * w2 x)``), a final LayerNorm (eps 1e-5). The key bias of
``attn.qkv`` is multiplied by the persistent buffer ``bias_mask`` (1 for q and v, 0 for k).

RoPE: axial 2-D rotary embedding on q and k of the *patch* tokens only (CLS and registers
untouched), computed inside ``forward`` from the patch grid of the input, so any
``H, W`` that are multiples of 16 work. Patch centres ``(i + 0.5)/h`` and ``(j + 0.5)/w``
are mapped to ``[-1, 1]``; ``angles = 2π·coord / periods`` for the y then the x
coordinate, tiled twice; rotation ``x·cos + rotate_half(x)·sin`` with the "halves"
convention. The periods are the persistent buffer ``rope_embed.periods`` [head_dim/4],
``base ** (2i / (head_dim/2))``, base 100. DINOv3's training-time RoPE augmentation
(shift, jitter, coordinate rescaling) is not implemented: the encoder is always in eval
mode, where it is off.

Shapes: ``B`` batch, ``H, W`` image size (multiples of 16), ``h = H/16``, ``w = W/16``,
``C`` embedding dim (384 S/S+, 768 B, 1024 L), ``R`` register tokens (4).

Weights are user-supplied (gated, see ``models/dinov3.md``); tests use random weights.

Modules: :mod:`.config` (variants and normalisations), :mod:`.model` (the encoder),
:mod:`.checkpoint` (reading, key mapping, variant inference, strict loading).
"""

from __future__ import annotations

from .checkpoint import (
    WEIGHTS_HELP,
    DINOv3CheckpointError,
    DINOv3WeightsNotFoundError,
    hf_to_official,
    infer_dinov3_config,
    load_dinov3,
    read_safetensors,
    rope_base_from_periods,
)
from .config import DINOV3_PRESETS, IMAGENET_MEAN, IMAGENET_STD, SAT493M_MEAN, SAT493M_STD, DINOv3Config, FfnType
from .model import DINOv3Encoder, DINOv3Output, apply_rope, rope_periods, rope_sin_cos

__all__ = [
    "DINOV3_PRESETS",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "SAT493M_MEAN",
    "SAT493M_STD",
    "WEIGHTS_HELP",
    "DINOv3CheckpointError",
    "DINOv3Config",
    "DINOv3Encoder",
    "DINOv3Output",
    "DINOv3WeightsNotFoundError",
    "FfnType",
    "apply_rope",
    "hf_to_official",
    "infer_dinov3_config",
    "load_dinov3",
    "read_safetensors",
    "rope_base_from_periods",
    "rope_periods",
    "rope_sin_cos",
]
