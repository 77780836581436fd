"""Typed configurations of the MASt3R-compatible backbone and the Splatt3R-style Gaussian head.

``BackboneConfig()`` is the released ``MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric`` network
(ViT-L/16 encoder, ViT-B decoders, ``catmlp+dpt`` heads); :meth:`BackboneConfig.tiny` is a
few-thousand-times smaller preset for tests. :meth:`BackboneConfig.from_args_string` reads the
constructor string stored in an official checkpoint's ``args.model`` (parsed by :mod:`.constructor`, never
evaluated).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args

from .constructor import ModelConfigError, parse_constructor_string

__all__ = [
    "ActivationMode",
    "BackboneConfig",
    "ConfMode",
    "DepthMode",
    "GaussianHeadConfig",
    "HeadType",
]

logger = logging.getLogger(__name__)

HeadType = Literal["catmlp+dpt", "gaussian_head"]
"""``catmlp+dpt``: MASt3R's heads. ``gaussian_head``: Splatt3R's (the same plus ``gaussian_dpt``, which
lives in :class:`~macsplat_cli.neural.gaussian_head.GaussianHead`)."""
DepthMode = Literal["exp", "linear"]
"""Point-map activation: ``exp`` gives ``v/|v| · expm1(|v|)``; ``linear`` keeps ``v``."""
ConfMode = Literal["exp"]
"""Confidence activation: ``vmin + exp(x)``, clipped at ``vmax``."""
ActivationMode = tuple[str, float, float]
"""``(mode, vmin, vmax)`` exactly as upstream writes it, e.g. ``("exp", 1.0, inf)``."""

_PATCH_SIZE = 16
# Bounds on model sizes read from untrusted files (every released MASt3R/DUSt3R/CroCo network is well inside).
MAX_DEPTH = 64
"""Most transformer blocks in the encoder or in each decoder."""
MAX_WIDTH = 8192
"""Widest token or DPT feature width."""
MAX_HEADS = 256
"""Most attention heads per block."""
MAX_DESC_DIM = 1024
"""Largest matching-descriptor dimension ``D``."""
MAX_MLP_RATIO = 16.0
"""Largest MLP hidden-width ratio."""
_OUTPUT_MODE = re.compile(r"^pts3d(\+gaussian)?\+desc(\d+)$")
_ROPE = re.compile(r"^RoPE(\d+(?:\.\d+)?)$")
_PATCH_EMBEDS = ("PatchEmbedDust3R", "ManyAR_PatchEmbed")
_MODEL_CLASSES = ("AsymmetricMASt3R",)
# Constructor kwargs accepted without effect: inference always runs with ``landscape_only=False``
# (upstream forces it too); ``use_offsets``/``sh_degree`` configure Splatt3R's Gaussian head, see
# GaussianHeadConfig.
_IGNORED_KWARGS = ("landscape_only", "use_offsets", "sh_degree")
# Upstream default of ``desc_conf_mode`` when a constructor string omits it (reference §1.1: Splatt3R's
# constructor omits it and gets desc_conf = 1 + exp(x)).
_DESC_CONF_MODE_WHEN_OMITTED: ActivationMode = ("exp", 1.0, math.inf)


@dataclass(frozen=True)
class BackboneConfig:
    """Architecture of :class:`~macsplat_cli.neural.backbone.MASt3RBackbone`.

    The defaults are the released MASt3R metric checkpoint (688,638,856 parameters).

    Args:
        img_size: training resolution (H, W) recorded by upstream; informational only, since RoPE
            works at any size that is a multiple of 16.
        patch_size: ViT patch size; only 16 is supported (the DPT's up-sampling factors assume it).
        enc_embed_dim: encoder width.
        enc_depth: number of encoder blocks.
        enc_num_heads: encoder attention heads.
        dec_embed_dim: decoder width.
        dec_depth: number of blocks in each of the two decoders.
        dec_num_heads: decoder attention heads.
        mlp_ratio: hidden width of every transformer MLP, relative to its input width.
        norm_im2_in_dec: LayerNorm (``norm_y``) on the other view's tokens before cross-attention.
        rope_freq: RoPE base frequency (``pos_embed='RoPE100'`` → 100).
        head_type: see :data:`HeadType`.
        local_feat_dim: descriptor dimension ``D`` (``output_mode='pts3d+desc24'`` → 24).
        two_confs: the local-feature MLP also predicts a descriptor confidence (only ``True`` is supported).
        depth_mode: point-map activation ``(mode, vmin, vmax)``; vmin/vmax must be ±inf.
        conf_mode: point-map confidence activation ``(mode, vmin, vmax)``.
        desc_conf_mode: descriptor-confidence activation ``(mode, vmin, vmax)``.
        local_mlp_ratio: hidden width of the local-feature MLP relative to its input
            (``enc_embed_dim + dec_embed_dim``).
        dpt_layer_dims: DPT reassemble widths at H/4, H/8, H/16, H/32.
        dpt_feature_dim: DPT fusion width.
        dpt_last_dim: width of the DPT head's last hidden convolution.
        mask_token: the model has CroCo's (unused) ``mask_token`` parameter ``[1, 1, dec_embed_dim]``.
    """

    img_size: tuple[int, int] = (512, 512)
    patch_size: int = _PATCH_SIZE
    enc_embed_dim: int = 1024
    enc_depth: int = 24
    enc_num_heads: int = 16
    dec_embed_dim: int = 768
    dec_depth: int = 12
    dec_num_heads: int = 12
    mlp_ratio: float = 4.0
    norm_im2_in_dec: bool = True
    rope_freq: float = 100.0
    head_type: HeadType = "catmlp+dpt"
    local_feat_dim: int = 24
    two_confs: bool = True
    depth_mode: ActivationMode = ("exp", -math.inf, math.inf)
    conf_mode: ActivationMode = ("exp", 1.0, math.inf)
    desc_conf_mode: ActivationMode = ("exp", 0.0, math.inf)
    local_mlp_ratio: float = 4.0
    dpt_layer_dims: tuple[int, int, int, int] = (96, 192, 384, 768)
    dpt_feature_dim: int = 256
    dpt_last_dim: int = 128
    mask_token: bool = True

    def __post_init__(self) -> None:
        if self.patch_size != _PATCH_SIZE:
            raise ModelConfigError(f"patch_size={self.patch_size} is not supported (only {_PATCH_SIZE})")
        # Bounds first: a config file is untrusted, and building a million blocks (even on ``meta``) takes minutes.
        _check_bound("enc_depth", self.enc_depth, MAX_DEPTH)
        _check_bound("dec_depth", self.dec_depth, MAX_DEPTH)
        _check_bound("enc_embed_dim", self.enc_embed_dim, MAX_WIDTH)
        _check_bound("dec_embed_dim", self.dec_embed_dim, MAX_WIDTH)
        _check_bound("enc_num_heads", self.enc_num_heads, MAX_HEADS)
        _check_bound("dec_num_heads", self.dec_num_heads, MAX_HEADS)
        _check_bound("local_feat_dim", self.local_feat_dim, MAX_DESC_DIM)
        _check_bound("dpt_feature_dim", self.dpt_feature_dim, MAX_WIDTH)
        _check_bound("dpt_last_dim", self.dpt_last_dim, MAX_WIDTH)
        for i, dim in enumerate(self.dpt_layer_dims):
            _check_bound(f"dpt_layer_dims[{i}]", dim, MAX_WIDTH)
        for name in ("mlp_ratio", "local_mlp_ratio"):
            ratio = getattr(self, name)
            if not (isinstance(ratio, (int, float)) and math.isfinite(ratio) and 0 < ratio <= MAX_MLP_RATIO):
                raise ModelConfigError(f"{name}={ratio} must be a number in (0, {MAX_MLP_RATIO:g}]")
        if not (isinstance(self.rope_freq, (int, float)) and math.isfinite(self.rope_freq) and self.rope_freq > 0):
            raise ModelConfigError(f"rope_freq={self.rope_freq} must be a positive finite number")
        for name in ("enc", "dec"):
            dim, heads = getattr(self, f"{name}_embed_dim"), getattr(self, f"{name}_num_heads")
            if dim <= 0 or heads <= 0 or dim % heads or (dim // heads) % 4:
                raise ModelConfigError(
                    f"{name}_embed_dim={dim} with {name}_num_heads={heads}: the head dimension must be a "
                    "positive multiple of 4 (2-D RoPE rotates two halves in pairs)"
                )
        if self.enc_depth <= 0 or self.dec_depth <= 0:
            raise ModelConfigError(f"enc_depth={self.enc_depth} and dec_depth={self.dec_depth} must be positive")
        if self.head_type not in get_args(HeadType):
            raise ModelConfigError(f"head_type={self.head_type!r} is not supported (one of {get_args(HeadType)})")
        if not self.two_confs:
            raise ModelConfigError("two_confs=False is not supported: MASt3R's descriptor head predicts a confidence")
        if self.local_feat_dim <= 0:
            raise ModelConfigError(f"local_feat_dim={self.local_feat_dim} must be positive")
        _check_mode("depth_mode", self.depth_mode, get_args(DepthMode))
        if self.depth_mode[1:] != (-math.inf, math.inf):
            raise ModelConfigError(f"depth_mode={self.depth_mode}: only unbounded (-inf, inf) depth is supported")
        _check_mode("conf_mode", self.conf_mode, get_args(ConfMode))
        _check_mode("desc_conf_mode", self.desc_conf_mode, get_args(ConfMode))
        dpt = (*self.dpt_layer_dims, self.dpt_feature_dim // 2, self.dpt_last_dim)
        if len(self.dpt_layer_dims) != 4 or min(dpt) <= 0:
            raise ModelConfigError(
                f"dpt_layer_dims={self.dpt_layer_dims} (4 entries), dpt_feature_dim={self.dpt_feature_dim} (≥ 2) "
                f"and dpt_last_dim={self.dpt_last_dim} must be positive"
            )
        if self.mlp_ratio <= 0 or self.local_mlp_ratio <= 0:
            raise ModelConfigError(f"mlp_ratio={self.mlp_ratio} and local_mlp_ratio={self.local_mlp_ratio} must be > 0")

    # ------------------------------------------------------------------ presets
    @classmethod
    def tiny(cls) -> BackboneConfig:
        """A small network with the official structure (for tests): a 64×48 pair runs in milliseconds."""
        return cls(
            img_size=(64, 64),
            enc_embed_dim=64,
            enc_depth=2,
            enc_num_heads=2,
            dec_embed_dim=32,
            dec_depth=3,
            dec_num_heads=2,
            local_mlp_ratio=1.0,
            dpt_layer_dims=(8, 16, 24, 32),
            dpt_feature_dim=16,
            dpt_last_dim=8,
        )

    # ------------------------------------------------------------------ derived values
    @property
    def dpt_hooks(self) -> tuple[int, int, int, int]:
        """Indices into the decoder token list (entry 0 = encoder output) that feed the DPT heads.

        ``(0, 6, 9, 12)`` for 12 decoder blocks; other depths use ``(0, d/2, 3d/4, d)`` rounded down,
        which is the same rule (the reference only states the 12-block values).
        """
        d = self.dec_depth
        return (0, d * 2 // 4, d * 3 // 4, d)

    @property
    def local_mlp_in_dim(self) -> int:
        """Input width of the local-feature MLP: encoder tokens concatenated with the last decoder tokens."""
        return self.enc_embed_dim + self.dec_embed_dim

    @property
    def local_mlp_hidden_dim(self) -> int:
        return int(self.local_mlp_ratio * self.local_mlp_in_dim)

    @property
    def local_mlp_out_dim(self) -> int:
        """``(D + 1)·16²`` values per patch: descriptor plus its confidence for every pixel of the patch."""
        return (self.local_feat_dim + int(self.two_confs)) * self.patch_size**2

    @property
    def output_mode(self) -> str:
        """Upstream's ``output_mode`` string for this configuration."""
        gauss = "+gaussian" if self.head_type == "gaussian_head" else ""
        return f"pts3d{gauss}+desc{self.local_feat_dim}"

    # ------------------------------------------------------------------ parsing
    @classmethod
    def from_args_string(cls, s: str) -> BackboneConfig:
        """Configuration from an official constructor string (``args.model`` of a MASt3R ``.pth``).

        Example: ``"AsymmetricMASt3R(enc_depth=24, ..., output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf))"``.
        The string is parsed with :func:`ast.parse` and never evaluated; see
        :func:`~.constructor.parse_constructor_string` for the accepted syntax and :meth:`from_kwargs` for the
        accepted keywords.

        Raises:
            ModelConfigError: on a syntax error, an unexpected construct, class or keyword, or an unsupported value.
        """
        name, kwargs = parse_constructor_string(s)
        if name not in _MODEL_CLASSES:
            raise ModelConfigError(f"model class {name!r} is not supported (expected one of {_MODEL_CLASSES})")
        return cls.from_kwargs(kwargs)

    @classmethod
    def from_kwargs(cls, kwargs: Mapping[str, Any]) -> BackboneConfig:
        """Configuration from upstream constructor keyword arguments (a parsed string or a ``config.json``).

        Accepted keys: ``enc_embed_dim, enc_depth, enc_num_heads, dec_embed_dim, dec_depth, dec_num_heads,
        mlp_ratio, norm_im2_in_dec, patch_size, img_size, pos_embed ('RoPE<f>'), patch_embed_cls
        ('PatchEmbedDust3R' | 'ManyAR_PatchEmbed', both give the same network at inference), head_type,
        output_mode ('pts3d+desc<D>' | 'pts3d+gaussian+desc<D>'), depth_mode, conf_mode, desc_conf_mode,
        two_confs``; macsplat's extensions for smaller networks (never written by upstream, emitted by
        :meth:`to_args_string` only when they differ from the released network): ``dpt_layer_dims,
        dpt_feature_dim, dpt_last_dim, local_mlp_ratio``; and, without effect, ``landscape_only, use_offsets,
        sh_degree``. Omitted keys take this
        class's defaults (the released network), except ``desc_conf_mode``, which takes upstream's
        default ``('exp', 1, inf)``. Lists are read as tuples and the strings ``"inf"``/``"-inf"`` as floats
        (JSON has no infinity literal in its standard).
        """
        kw = {k: _jsonish_to_python(v) for k, v in kwargs.items()}
        out: dict[str, Any] = {"desc_conf_mode": _DESC_CONF_MODE_WHEN_OMITTED}
        ints = ("enc_embed_dim", "enc_depth", "enc_num_heads", "dec_embed_dim", "dec_depth", "dec_num_heads")
        for key, value in kw.items():
            if key in ints or key == "patch_size":
                out[key] = _expect(key, value, int)
            elif key == "mlp_ratio":
                out[key] = float(_expect(key, value, (int, float)))
            elif key in ("norm_im2_in_dec", "two_confs"):
                out[key] = _expect(key, value, bool)
            elif key == "img_size":
                if isinstance(value, int) and not isinstance(value, bool):
                    value = (value, value)
                if not (isinstance(value, tuple) and len(value) == 2 and all(_is_int(v) for v in value)):
                    raise ModelConfigError(f"img_size must be an int or a pair of ints, got {value!r}")
                out[key] = (int(value[0]), int(value[1]))
            elif key == "pos_embed":
                m = _ROPE.match(str(_expect(key, value, str)))
                if m is None:
                    raise ModelConfigError(f"pos_embed={value!r} is not supported (only 'RoPE<freq>', e.g. 'RoPE100')")
                out["rope_freq"] = float(m.group(1))
            elif key == "patch_embed_cls":
                if value not in _PATCH_EMBEDS:
                    raise ModelConfigError(f"patch_embed_cls={value!r} is not supported (one of {_PATCH_EMBEDS})")
            elif key == "head_type":
                out[key] = _expect(key, value, str)
            elif key == "output_mode":
                m = _OUTPUT_MODE.match(str(_expect(key, value, str)))
                if m is None:
                    raise ModelConfigError(
                        f"output_mode={value!r} is not supported (expected 'pts3d+desc<D>' or 'pts3d+gaussian+desc<D>')"
                    )
                out["local_feat_dim"] = int(m.group(2))
            elif key in ("depth_mode", "conf_mode", "desc_conf_mode"):
                out[key] = _activation_mode(key, value)
            elif key == "dpt_layer_dims":
                if not (isinstance(value, tuple) and len(value) == 4 and all(_is_int(v) for v in value)):
                    raise ModelConfigError(f"dpt_layer_dims must be 4 ints, got {value!r}")
                out[key] = value
            elif key in ("dpt_feature_dim", "dpt_last_dim"):
                out[key] = _expect(key, value, int)
            elif key == "local_mlp_ratio":
                out[key] = float(_expect(key, value, (int, float)))
            elif key in _IGNORED_KWARGS:
                logger.debug("model kwarg %s=%r has no effect on the backbone", key, value)
            else:
                raise ModelConfigError(f"unexpected model keyword {key!r} (= {value!r})")
        return cls(**out)

    def to_kwargs(self) -> dict[str, Any]:
        """Upstream constructor kwargs for this configuration (the inverse of :meth:`from_kwargs`)."""
        return {
            "pos_embed": f"RoPE{self.rope_freq:g}",
            "patch_embed_cls": "PatchEmbedDust3R",
            "img_size": self.img_size,
            "head_type": self.head_type,
            "output_mode": self.output_mode,
            "depth_mode": self.depth_mode,
            "conf_mode": self.conf_mode,
            "enc_embed_dim": self.enc_embed_dim,
            "enc_depth": self.enc_depth,
            "enc_num_heads": self.enc_num_heads,
            "dec_embed_dim": self.dec_embed_dim,
            "dec_depth": self.dec_depth,
            "dec_num_heads": self.dec_num_heads,
            "two_confs": self.two_confs,
            "desc_conf_mode": self.desc_conf_mode,
            **{k: getattr(self, k) for k in _EXTENSION_KWARGS if getattr(self, k) != getattr(_RELEASED, k)},
        }

    def to_args_string(self) -> str:
        """An upstream-style constructor string (``inf`` written as a bare name, as upstream does)."""

        def fmt(v: Any) -> str:
            if isinstance(v, tuple):
                return "(" + ", ".join(fmt(x) for x in v) + ")"
            if isinstance(v, float) and math.isinf(v):
                return "inf" if v > 0 else "-inf"
            return repr(v)

        return "AsymmetricMASt3R(" + ", ".join(f"{k}={fmt(v)}" for k, v in self.to_kwargs().items()) + ")"

    def replace(self, **changes: Any) -> BackboneConfig:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class GaussianHeadConfig:
    """Splatt3R's Gaussian head (reference §3.2).

    Args:
        sh_coeffs: SH coefficients per colour channel ``K`` (Splatt3R's ``sh_degree``, which counts
            coefficients, not the degree: 1 → DC only, the released model). Must be 1, 4, 9 or 16.
        use_offsets: means = point map + predicted offset (else the point map itself).
        detach_points: the means use the point map without gradient (Splatt3R's behaviour).
        max_scale: the Gaussians' scales are clamped at this, in the point map's units (None: no cap, as
            Splatt3R; the MAC-Splat release caps them at 0.5 in training and at test).
    """

    sh_coeffs: int = 1
    use_offsets: bool = True
    detach_points: bool = True
    max_scale: float | None = None

    def __post_init__(self) -> None:
        if self.sh_coeffs not in (1, 4, 9, 16):
            raise ModelConfigError(f"sh_coeffs={self.sh_coeffs} must be (degree + 1)² for a degree 0..3")
        if self.max_scale is not None and not (math.isfinite(self.max_scale) and self.max_scale > 0):
            raise ModelConfigError(f"max_scale={self.max_scale} must be a finite number > 0 (or None: no cap)")

    @property
    def out_channels(self) -> int:
        """Channels of ``gaussian_dpt``: offset 3 + scale 3 + rotation 4 + SH 3·K + opacity 1."""
        return 3 + 3 + 4 + 3 * self.sh_coeffs + 1


_EXTENSION_KWARGS = (
    "mlp_ratio",
    "norm_im2_in_dec",
    "dpt_layer_dims",
    "dpt_feature_dim",
    "dpt_last_dim",
    "local_mlp_ratio",
)


def _jsonish_to_python(v: Any, *, in_sequence: bool = False) -> Any:
    if isinstance(v, list | tuple):
        return tuple(_jsonish_to_python(x, in_sequence=True) for x in v)
    if in_sequence and isinstance(v, str) and v.strip().lower() in ("inf", "-inf", "+inf", "infinity", "-infinity"):
        return float(v)
    return v


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _expect(key: str, value: Any, types: type | tuple[type, ...]) -> Any:
    ok = isinstance(value, types)
    if ok and isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        ok = False
    if not ok:
        raise ModelConfigError(f"{key}={value!r} has the wrong type ({type(value).__name__})")
    return value


def _activation_mode(key: str, value: Any) -> ActivationMode:
    if isinstance(value, str):
        value = (value, -math.inf, math.inf)
    if not (
        isinstance(value, tuple)
        and len(value) == 3
        and isinstance(value[0], str)
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value[1:])
    ):
        raise ModelConfigError(f"{key}={value!r} must be (mode, vmin, vmax)")
    return (value[0], float(value[1]), float(value[2]))


def _check_bound(key: str, value: Any, most: int) -> None:
    """Raise :class:`ModelConfigError` unless ``value`` is an int in ``[1, most]``."""
    if not _is_int(value) or not 1 <= value <= most:
        raise ModelConfigError(f"{key}={value!r} is out of range (a whole number from 1 to {most})")


def _check_mode(key: str, mode: ActivationMode, allowed: tuple[str, ...]) -> None:
    if not (isinstance(mode, tuple) and len(mode) == 3 and mode[0] in allowed):
        raise ModelConfigError(f"{key}={mode!r} is not supported (mode must be one of {allowed})")
    if not mode[1] < mode[2] or math.isnan(mode[1]) or math.isnan(mode[2]):
        raise ModelConfigError(f"{key}={mode!r}: vmin must be below vmax")


_RELEASED = BackboneConfig()  # after the helpers its validation uses
