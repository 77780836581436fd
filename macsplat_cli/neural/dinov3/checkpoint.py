"""Loading DINOv3 weights: the official and Hugging Face layouts, variant inference, strict checks.

See :func:`load_dinov3`; the key mapping is :func:`hf_to_official`, the variant inference
:func:`infer_dinov3_config`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import torch

from ..._limits import read_json_file
from ..._state_dict import StateDictError, check_state_dict_keys, log_sha256
from ..._state_dict import read_safetensors as _read_safetensors
from ..constructor import ModelConfigError
from .config import DINOV3_PRESETS, SAT493M_MEAN, SAT493M_STD, DINOv3Config
from .model import DINOv3Encoder, rope_periods

__all__ = [
    "WEIGHTS_HELP",
    "DINOv3CheckpointError",
    "DINOv3WeightsNotFoundError",
    "hf_to_official",
    "infer_dinov3_config",
    "load_dinov3",
    "read_safetensors",
    "rope_base_from_periods",
]

logger = logging.getLogger(__name__)

# Heads of the released widths, for the HF layout without a config.json (head dim 64, 128 for 7B).
_HEADS_BY_WIDTH = {384: 6, 768: 12, 1024: 16, 1280: 20, 4096: 32}
_DEFAULT_ROPE_BASE = 100.0
# Relative tolerance on stored RoPE periods: bfloat16 keeps 8 significant bits, so rounding moves a
# period by at most 2**-8 of its value; plus float32 slack for periods computed in float32 first.
_PERIODS_RTOL = 2.0**-8 + 1e-6

WEIGHTS_HELP = (
    "DINOv3 weights are gated and never downloaded by macsplat: request them through the form on ai.meta.com "
    "(linked from github.com/facebookresearch/dinov3; the e-mailed URLs serve the official .pth files), or accept "
    "the licence of a facebook/dinov3-*-pretrain-* repository on Hugging Face and download its folder "
    "(config.json + model.safetensors). See models/dinov3.md."
)


class DINOv3CheckpointError(StateDictError):
    """A DINOv3 weight file is unreadable or does not match the model.

    Attributes (of :class:`StateDictError`):
        key: the first offending state-dict key (official naming), or None.
        file_shape: its shape in the file (None when the file lacks it).
        model_shape: its shape in the model (None when the model has no such key); also ``expected_shape``.
    """

    def __init__(
        self,
        message: str,
        *,
        key: str | None = None,
        file_shape: tuple[int, ...] | None = None,
        model_shape: tuple[int, ...] | None = None,
        expected_shape: tuple[int, ...] | None = None,
        missing_keys: Iterable[str] = (),
        unexpected_keys: Iterable[str] = (),
    ) -> None:
        super().__init__(
            message,
            key=key,
            file_shape=file_shape,
            model_shape=model_shape if model_shape is not None else expected_shape,
            missing_keys=missing_keys,
            unexpected_keys=unexpected_keys,
        )

    @property
    def expected_shape(self) -> tuple[int, ...] | None:
        """The key's shape in the model (:attr:`model_shape`)."""
        return self.model_shape


class DINOv3WeightsNotFoundError(DINOv3CheckpointError, FileNotFoundError):
    """The DINOv3 weight file or folder does not exist; the message says where to get it."""


def read_safetensors(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Read a ``.safetensors`` file into CPU tensors (:func:`macsplat_cli._state_dict.read_safetensors`).

    Raises:
        DINOv3CheckpointError: the file is truncated or its header is malformed.
    """
    return _read_safetensors(path, DINOv3CheckpointError)


_HF_BLOCK = re.compile(r"^(?:model\.)?layer\.(\d+)\.(.+)$")
_HF_TOP = {
    "embeddings.cls_token": "cls_token",
    "embeddings.mask_token": "mask_token",
    "embeddings.register_tokens": "storage_tokens",
    "embeddings.patch_embeddings.weight": "patch_embed.proj.weight",
    "embeddings.patch_embeddings.bias": "patch_embed.proj.bias",
    "norm.weight": "norm.weight",
    "norm.bias": "norm.bias",
}
_HF_BLOCK_SIMPLE = {
    "norm1.weight": "norm1.weight",
    "norm1.bias": "norm1.bias",
    "norm2.weight": "norm2.weight",
    "norm2.bias": "norm2.bias",
    "attention.o_proj.weight": "attn.proj.weight",
    "attention.o_proj.bias": "attn.proj.bias",
    "layer_scale1.lambda1": "ls1.gamma",
    "layer_scale2.lambda1": "ls2.gamma",
}
_HF_QKV = re.compile(r"^attention\.([qkv])_proj\.(weight|bias)$")
_HF_FFN = re.compile(r"^mlp\.(gate_proj|up_proj|down_proj)\.(weight|bias)$")


def hf_to_official(state_dict: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Map a Hugging Face ``DINOv3ViTModel`` state dict onto the official key names.

    ``q/k/v_proj`` are stacked into ``attn.qkv`` (a missing key bias becomes zeros and
    ``bias_mask`` is rebuilt: 1 for q and v, 0 for k — or 1 for k too when the file has a
    key bias), ``o_proj`` → ``attn.proj``, ``layer_scale{1,2}.lambda1`` → ``ls{1,2}.gamma``,
    ``mlp.up_proj/down_proj`` → ``mlp.fc1/fc2`` (SwiGLU: ``gate/up/down_proj`` →
    ``w1/w2/w3``), ``embeddings.*`` → ``cls_token``, ``storage_tokens``, ``mask_token``
    (reshaped to [1, C]), ``patch_embed.proj.*``. Keys may carry the in-memory
    ``model.`` prefix on ``layer.*`` or not (hub files). ``rope_embed.periods`` is *not*
    produced (HF has no such key; :func:`load_dinov3` recomputes it). ``*.inv_freq``
    (a derived RoPE buffer) is dropped.

    Raises:
        DINOv3CheckpointError: a key is unknown, or a block lacks one of q/k/v.
    """
    out: dict[str, torch.Tensor] = {}
    blocks: dict[int, dict[str, torch.Tensor]] = {}
    for key, t in state_dict.items():
        if key.endswith("inv_freq"):
            continue
        if key in _HF_TOP:
            out[_HF_TOP[key]] = t.reshape(1, -1) if key == "embeddings.mask_token" else t
            continue
        m = _HF_BLOCK.match(key)
        if m is None:
            raise DINOv3CheckpointError(
                f"unexpected key {key!r} with shape {list(t.shape)} in a Hugging Face DINOv3 state dict",
                key=key,
                file_shape=tuple(t.shape),
            )
        blocks.setdefault(int(m.group(1)), {})[m.group(2)] = t
    for i in sorted(blocks):
        parts = blocks[i]
        if "mlp.gate_proj.weight" in parts:  # SwiGLU
            ffn_names = {"gate_proj": "w1", "up_proj": "w2", "down_proj": "w3"}
        else:
            ffn_names = {"up_proj": "fc1", "down_proj": "fc2"}
        for rest, t in parts.items():
            if rest in _HF_BLOCK_SIMPLE:
                out[f"blocks.{i}.{_HF_BLOCK_SIMPLE[rest]}"] = t
            elif (fm := _HF_FFN.match(rest)) is not None and fm.group(1) in ffn_names:
                out[f"blocks.{i}.mlp.{ffn_names[fm.group(1)]}.{fm.group(2)}"] = t
            elif _HF_QKV.match(rest) is None:
                key = f"layer.{i}.{rest}"
                raise DINOv3CheckpointError(
                    f"unexpected key {key!r} with shape {list(t.shape)} in a Hugging Face DINOv3 state dict",
                    key=key,
                    file_shape=tuple(t.shape),
                )
        weights = []
        for x in "qkv":
            w = parts.get(f"attention.{x}_proj.weight")
            if w is None:
                key = f"layer.{i}.attention.{x}_proj.weight"
                raise DINOv3CheckpointError(f"missing key {key!r} in a Hugging Face DINOv3 state dict", key=key)
            weights.append(w)
        out[f"blocks.{i}.attn.qkv.weight"] = torch.cat(weights, dim=0)
        qb, kb, vb = (parts.get(f"attention.{x}_proj.bias") for x in "qkv")
        if qb is not None or kb is not None or vb is not None:
            c = weights[0].shape[0]
            zeros = weights[0].new_zeros(c)
            out[f"blocks.{i}.attn.qkv.bias"] = torch.cat([b if b is not None else zeros for b in (qb, kb, vb)])
            mask = torch.ones(3 * c, dtype=weights[0].dtype)
            if kb is None:
                mask[c : 2 * c] = 0.0
            out[f"blocks.{i}.attn.qkv.bias_mask"] = mask
    return out


def _need(state_dict: Mapping[str, torch.Tensor], key: str, what: str) -> torch.Tensor:
    t = state_dict.get(key)
    if t is None:
        raise DINOv3CheckpointError(f"cannot infer the DINOv3 variant: key {key!r} missing ({what})", key=key)
    return t


def rope_base_from_periods(periods: torch.Tensor) -> float:
    """The RoPE base of the ``rope_embed.periods`` buffer ``base ** (i / P)``, ``i < P``. periods: [P]

    Checkpoints store the periods in float32 or bfloat16, so a power of one period is not the
    base (``periods[1] ** P`` is 100.0001 for float32 and 102.94 for bfloat16 periods of ViT-L).
    A preset's base is returned exactly when every period is within bfloat16 rounding of its
    periods (computed in float64); any other base is the float64 least-squares fit of
    ``log periods[i] = (i / P) · log base``, to 4 significant digits. Meta tensors and ``P < 2``
    give the default base, 100.

    Raises:
        DINOv3CheckpointError: a period is not positive and finite.
    """
    n = int(periods.numel())
    if n < 2 or periods.device.type == "meta":
        return _DEFAULT_ROPE_BASE
    p = periods.detach().to(device="cpu", dtype=torch.float64).reshape(-1)
    if not bool(torch.isfinite(p).all()) or bool((p <= 0).any()):
        raise DINOv3CheckpointError(
            f"rope_embed.periods must be positive and finite, got {p.tolist()}",
            key="rope_embed.periods",
            file_shape=tuple(periods.shape),
        )
    exponents = torch.arange(n, dtype=torch.float64) / n  # i / P
    for base in sorted({cfg.rope_base for cfg in DINOV3_PRESETS.values()}):
        if torch.allclose(p, base**exponents, rtol=_PERIODS_RTOL, atol=0.0):
            return base
    log_base = float((exponents * p.log()).sum() / exponents.square().sum())
    return float(f"{math.exp(log_base):.4g}")


def infer_dinov3_config(state_dict: Mapping[str, torch.Tensor], *, num_heads: int | None = None) -> DINOv3Config:
    """Infer the variant from the shapes of an official-layout state dict (works on ``meta`` tensors).

    Width from ``cls_token``, patch size from ``patch_embed.proj.weight``, registers from
    ``storage_tokens``, depth from the ``blocks.{i}.norm1.weight`` keys, FFN type and width
    from ``blocks.0.mlp.{fc1,w1}.weight``, biases from the presence of their keys, the head
    dim from ``rope_embed.periods`` (4 × its length; else ``num_heads``, else the released
    models' head count for that width) and the RoPE base from the periods
    (:func:`rope_base_from_periods`, which accepts float32 and bfloat16 periods). A ViT-L with a
    ``local_cls_norm`` is the SAT-493M (satellite) model and gets its image normalisation.
    Named presets are recognised; anything else is named ``custom-…`` (with ``-rope{base}``
    when the base is not 100).

    Raises:
        DINOv3CheckpointError: a key needed for the inference is missing (not a DINOv3 ViT), or
            the periods are not positive and finite.
    """
    if "cls_token" not in state_dict and any(k.startswith(("downsample_layers", "stages")) for k in state_dict):
        raise DINOv3CheckpointError("a DINOv3 ConvNeXt checkpoint: only the ViT variants are supported", key=None)
    c = int(_need(state_dict, "cls_token", "not a DINOv3 ViT checkpoint").shape[-1])
    patch = int(_need(state_dict, "patch_embed.proj.weight", "patch embedding").shape[-1])
    storage = state_dict.get("storage_tokens")
    n_storage = int(storage.shape[1]) if storage is not None and storage.dim() == 3 else 0
    depth = 0
    while f"blocks.{depth}.norm1.weight" in state_dict:
        depth += 1
    if depth == 0:
        _need(state_dict, "blocks.0.norm1.weight", "no transformer block")
    swiglu = "blocks.0.mlp.w1.weight" in state_dict
    first_ffn = "blocks.0.mlp.w1" if swiglu else "blocks.0.mlp.fc1"
    hidden = int(_need(state_dict, f"{first_ffn}.weight", "FFN").shape[0])
    heads, rope_base = _heads_and_rope_base(state_dict, c, num_heads)
    untie = "local_cls_norm.weight" in state_dict
    try:
        base = DINOv3Config(
            name="custom",
            embed_dim=c,
            depth=depth,
            num_heads=heads,
            ffn="swiglu" if swiglu else "mlp",
            ffn_hidden_dim=hidden,
            patch_size=patch,
            n_storage_tokens=n_storage,
            qkv_bias="blocks.0.attn.qkv.bias" in state_dict,
            proj_bias="blocks.0.attn.proj.bias" in state_dict,
            ffn_bias=f"{first_ffn}.bias" in state_dict,
            rope_base=rope_base,
            untie_global_and_local_cls_norm=untie,
        )
    except ModelConfigError as e:
        raise DINOv3CheckpointError(f"the weights describe an unsupported DINOv3 variant: {e}", key=None) from None
    return _named(base, untie)


def _heads_and_rope_base(state_dict: Mapping[str, torch.Tensor], c: int, num_heads: int | None) -> tuple[int, float]:
    """The head count and the RoPE base of a width-``c`` ViT: from ``rope_embed.periods`` when the file has
    them, else ``num_heads``, else the released models' head count for that width (and the default base)."""
    periods = state_dict.get("rope_embed.periods")
    rope_base = _DEFAULT_ROPE_BASE
    if periods is not None and periods.dim() == 1 and periods.numel() > 0:
        head_dim = 4 * int(periods.numel())
        heads = c // head_dim if c % head_dim == 0 else 0
        rope_base = rope_base_from_periods(periods)
    elif num_heads:
        if not isinstance(num_heads, int) or isinstance(num_heads, bool):
            raise DINOv3CheckpointError(f"num_attention_heads={num_heads!r} is not a whole number", key=None)
        heads = num_heads
    else:
        heads = _HEADS_BY_WIDTH.get(c, c // 64)
        logger.warning("the DINOv3 weights do not give the head count: assuming %d heads for width %d", heads, c)
    if heads <= 0 or c % heads != 0 or (c // heads) % 4 != 0:
        raise DINOv3CheckpointError(f"cannot infer the DINOv3 head count for width {c}", key="rope_embed.periods")
    return heads, rope_base


def _named(base: DINOv3Config, untie: bool) -> DINOv3Config:
    """``base`` (named ``custom``) under its preset's name when it is one (an untied ViT-L: the SAT-493M model,
    with its normalisation), else ``custom-{width}d-{depth}x{heads}h-{ffn}{hidden}[-rope{base}]``."""
    for name, preset in DINOV3_PRESETS.items():
        if name == "tiny":
            continue
        if dataclasses.replace(base, name=name, untie_global_and_local_cls_norm=False) == preset:
            if not untie:
                return preset
            if name == "vitl16":
                logger.info("DINOv3 ViT-L with a local_cls_norm: the SAT-493M weights, using their normalisation")
                return dataclasses.replace(
                    preset,
                    name="vitl16-sat493m",
                    untie_global_and_local_cls_norm=True,
                    image_mean=SAT493M_MEAN,
                    image_std=SAT493M_STD,
                )
            return dataclasses.replace(base, name=f"{name}-untied")
    c, depth, heads, hidden = base.embed_dim, base.depth, base.num_heads, base.ffn_hidden_dim
    rope = f"-rope{base.rope_base:g}" if base.rope_base != _DEFAULT_ROPE_BASE else ""
    return dataclasses.replace(base, name=f"custom-{c}d-{depth}x{heads}h-{base.ffn}{hidden}{rope}")


def _not_found(what: Path, detail: str = "") -> DINOv3WeightsNotFoundError:
    return DINOv3WeightsNotFoundError(f"DINOv3 weights not found: {what}{detail}. {WEIGHTS_HELP}")


def _read_hf_folder(folder: Path) -> tuple[dict[str, torch.Tensor], dict]:
    single = folder / "model.safetensors"
    index = folder / "model.safetensors.index.json"
    files: list[Path]
    if single.is_file():
        files = [single]
    elif index.is_file():
        data = read_json_file(index, DINOv3CheckpointError, "a safetensors index")
        weight_map = data.get("weight_map") if isinstance(data, dict) else None
        if not isinstance(weight_map, dict) or not all(isinstance(v, str) for v in weight_map.values()):
            raise DINOv3CheckpointError(f"{index}: unreadable safetensors index: no 'weight_map' of file names")
        files = [folder / name for name in dict.fromkeys(weight_map.values())]
    else:
        raise _not_found(single, f" (the folder {folder} has no model.safetensors)")
    sd: dict[str, torch.Tensor] = {}
    for f in files:
        if not f.is_file():
            raise _not_found(f)
        log_sha256(f, logger, "DINOv3 weights")
        sd.update(read_safetensors(f))
    hf_config: dict = {}
    cfg_path = folder / "config.json"
    if cfg_path.is_file():
        hf_config = read_json_file(cfg_path, DINOv3CheckpointError, "a config.json")
        if not isinstance(hf_config, dict):
            raise DINOv3CheckpointError(f"{cfg_path}: unreadable config.json: not a JSON object")
    else:
        logger.warning("%s has no config.json: assuming the released head count for the width", folder)
    return sd, hf_config


def _read_file(path: Path) -> dict[str, torch.Tensor]:
    log_sha256(path, logger, "DINOv3 weights")
    if path.suffix == ".safetensors":
        return read_safetensors(path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load's exception types are unspecified (IndexError on some garbage)
        raise DINOv3CheckpointError(f"{path}: not a readable PyTorch checkpoint: {type(e).__name__}: {e}") from e
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise DINOv3CheckpointError(
            f"{path}: expected a plain state dict (a mapping of names to tensors), got {type(obj).__name__}"
        )
    return dict(obj)


def load_dinov3(
    path: str | os.PathLike[str],
    config: DINOv3Config | None = None,
    *,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> DINOv3Encoder:
    """Load a frozen :class:`DINOv3Encoder` from user-supplied weights.

    Accepted layouts (told apart by their keys, not the file name):

    * the official ``.pth`` (a plain state dict, read with ``torch.load(weights_only=True)``);
    * a Hugging Face folder: ``config.json`` + ``model.safetensors`` (or a sharded
      ``model.safetensors.index.json``), keys mapped by :func:`hf_to_official`;
    * a single ``.safetensors`` file in either key layout.

    The sha256 of each weight file is logged at debug level (record it in ``models/dinov3.md``).

    Args:
        path: the ``.pth`` / ``.safetensors`` file or the HF folder.
        config: the expected variant; None infers it from the tensor shapes (:func:`infer_dinov3_config`).
        device: where the encoder lives.
        dtype: parameter dtype of the encoder (float32 by default; checkpoints are converted).

    Returns:
        The encoder in eval mode with ``requires_grad=False`` everywhere.

    Raises:
        DINOv3WeightsNotFoundError: the file or folder does not exist (the message says where to get weights).
        DINOv3CheckpointError: unreadable file, or a key missing / unexpected / of another shape than
            ``config`` (the message names the first such key, in file order then the model's missing
            keys, and both shapes).
    """
    p = Path(path)
    sd, hf_config, layout = _read_weights(p)
    try:
        cfg = config or infer_dinov3_config(sd, num_heads=hf_config.get("num_attention_heads"))
    except DINOv3CheckpointError as e:
        raise DINOv3CheckpointError(f"{p}: {e}", key=e.key) from None
    if config is None and hf_config:
        cfg = _with_hf_config(cfg, hf_config, p)
    if layout == "huggingface" and "rope_embed.periods" not in sd:
        sd["rope_embed.periods"] = rope_periods(cfg.head_dim, cfg.rope_base)

    with torch.device("meta"):
        encoder = DINOv3Encoder(cfg)
    expected = {k: v.shape for k, v in encoder.state_dict().items()}
    check_state_dict_keys(expected, sd, DINOv3CheckpointError, source=str(p), model=f"DINOv3 {cfg.name}")
    encoder.to_empty(device="cpu")
    encoder.load_state_dict(sd, strict=True)
    encoder = encoder.to(device=device, dtype=dtype)
    encoder.rope_embed.periods = sd["rope_embed.periods"].to(device=device, dtype=torch.float32)  # keep fp32
    encoder.requires_grad_(False)
    encoder.eval()
    n_params = sum(t.numel() for t in encoder.parameters())
    logger.info("loaded DINOv3 %s (%s layout, %.1fM parameters) from %s", cfg.name, layout, n_params / 1e6, p)
    return encoder


def _read_weights(p: Path) -> tuple[dict[str, torch.Tensor], dict, str]:
    """``(official-layout state dict, the folder's config.json or {}, "official" | "huggingface")``."""
    if not p.exists():
        raise _not_found(p)
    hf_config: dict = {}
    if p.is_dir():
        sd, hf_config = _read_hf_folder(p)
    else:
        sd = _read_file(p)
    layout = "official"
    if any(k.startswith("embeddings.") for k in sd):
        layout = "huggingface"
        try:
            sd = hf_to_official(sd)
        except DINOv3CheckpointError as e:
            raise DINOv3CheckpointError(f"{p}: {e}", key=e.key, file_shape=e.file_shape) from None
    return sd, hf_config, layout


def _with_hf_config(cfg: DINOv3Config, hf_config: dict, p: Path) -> DINOv3Config:
    """The inferred ``cfg`` checked against a Hugging Face ``config.json`` (width, activation), with its
    ``layer_norm_eps`` and ``rope_theta``."""
    width = hf_config.get("hidden_size", cfg.embed_dim)
    if width != cfg.embed_dim:
        raise DINOv3CheckpointError(
            f"{p}: config.json says hidden_size {width} but the weights have width {cfg.embed_dim}",
            key="embeddings.cls_token",
        )
    act = "silu" if cfg.ffn == "swiglu" else "gelu"
    if hf_config.get("hidden_act", act) != act:
        raise DINOv3CheckpointError(
            f"{p}: config.json hidden_act {hf_config['hidden_act']!r} is not supported "
            f"(DINOv3 uses {act!r} with a {cfg.ffn} FFN)"
        )
    try:
        cfg = dataclasses.replace(
            cfg,
            norm_eps=float(hf_config.get("layer_norm_eps", cfg.norm_eps)),
            rope_base=float(hf_config.get("rope_theta", cfg.rope_base)),
        )
    except (TypeError, ValueError) as e:  # ModelConfigError is a ValueError
        raise DINOv3CheckpointError(f"{p}: config.json: unsupported layer_norm_eps or rope_theta: {e}") from None
    return cfg
