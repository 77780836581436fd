"""Tests for the frozen DINOv3 encoder and its checkpoint loader (random weights only).

The expected key names and shapes are written out (``official_spec`` in ``support/checkpoints.py``) from the
reference's listing of the official state dict, not read from the module under test; the forward pass is
compared with a naive re-implementation (unfold patch embedding, explicit loops for the
RoPE angles, complex-number rotation, explicit softmax attention) in float64.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from macsplat_cli.errors import InputError, ShapeError
from macsplat_cli.neural.dinov3 import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    SAT493M_MEAN,
    SAT493M_STD,
    DINOv3CheckpointError,
    DINOv3Config,
    DINOv3Encoder,
    DINOv3WeightsNotFoundError,
    apply_rope,
    hf_to_official,
    infer_dinov3_config,
    load_dinov3,
    read_safetensors,
    rope_base_from_periods,
    rope_periods,
    rope_sin_cos,
)

from support.checkpoints import official_spec, random_official_state_dict
from support.numerics import forward_rel_tol, gamma, max_rel_err, unit_roundoff

TINY = DINOv3Config.preset("tiny")
U32 = unit_roundoff(torch.float32)
TINY_SWIGLU = dataclasses.replace(TINY, name="tiny-swiglu", ffn="swiglu", ffn_hidden_dim=96)


# ------------------------------------------------------------------------------------------------
# Helpers: a test-side HF converter and writer (the official layout: support/checkpoints.py)
# ------------------------------------------------------------------------------------------------


def official_to_hf(sd: dict[str, torch.Tensor], *, prefix: str = "") -> dict[str, torch.Tensor]:
    """Official → Hugging Face keys, following the reference's mapping table (§1.4)."""
    out: dict[str, torch.Tensor] = {}
    for key, t in sd.items():
        if key in ("rope_embed.periods",) or key.endswith("bias_mask"):
            continue
        if key == "cls_token":
            out["embeddings.cls_token"] = t
        elif key == "mask_token":
            out["embeddings.mask_token"] = t.reshape(1, 1, -1)
        elif key == "storage_tokens":
            out["embeddings.register_tokens"] = t
        elif key.startswith("patch_embed.proj."):
            out["embeddings.patch_embeddings." + key.split(".")[-1]] = t
        elif key.startswith("norm."):
            out[key] = t
        else:
            _, i, rest = key.split(".", 2)
            b = f"{prefix}layer.{i}."
            c = t.shape[0] // 3
            if rest == "attn.qkv.weight":
                for j, x in enumerate("qkv"):
                    out[b + f"attention.{x}_proj.weight"] = t[j * c : (j + 1) * c]
            elif rest == "attn.qkv.bias":
                out[b + "attention.q_proj.bias"] = t[:c]
                out[b + "attention.v_proj.bias"] = t[2 * c :]
            else:
                rename = {
                    "attn.proj": "attention.o_proj",
                    "ls1.gamma": "layer_scale1.lambda1",
                    "ls2.gamma": "layer_scale2.lambda1",
                    "mlp.fc1": "mlp.up_proj",
                    "mlp.fc2": "mlp.down_proj",
                    "mlp.w1": "mlp.gate_proj",
                    "mlp.w2": "mlp.up_proj",
                    "mlp.w3": "mlp.down_proj",
                }
                for old, new in rename.items():
                    if rest.startswith(old):
                        rest = new + rest[len(old) :]
                        break
                out[b + rest] = t
    return out


def write_safetensors(path: Path, sd: dict[str, torch.Tensor]) -> None:
    """A minimal safetensors writer (8-byte header length, JSON header, little-endian data)."""
    names = {torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16", torch.int64: "I64"}
    header: dict[str, dict] = {"__metadata__": {"format": "pt"}}
    blobs: list[bytes] = []
    offset = 0
    for key, t in sd.items():
        raw = t.contiguous().view(torch.uint8).numpy().tobytes() if t.numel() else b""
        header[key] = {"dtype": names[t.dtype], "shape": list(t.shape), "data_offsets": [offset, offset + len(raw)]}
        blobs.append(raw)
        offset += len(raw)
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    path.write_bytes(len(text).to_bytes(8, "little") + text + b"".join(blobs))


def write_hf_folder(folder: Path, sd_official: dict[str, torch.Tensor], cfg: DINOv3Config) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    write_safetensors(folder / "model.safetensors", official_to_hf(sd_official))
    hf_cfg = {
        "model_type": "dinov3_vit",
        "patch_size": 16,
        "hidden_size": cfg.embed_dim,
        "intermediate_size": cfg.ffn_hidden_dim,
        "num_hidden_layers": cfg.depth,
        "num_attention_heads": cfg.num_heads,
        "num_register_tokens": 4,
        "layerscale_value": 1.0,
        "use_gated_mlp": cfg.ffn == "swiglu",  # transformers 5.23's name (the reference says use_swiglu_ffn)
        "hidden_act": "silu" if cfg.ffn == "swiglu" else "gelu",
        "layer_norm_eps": 1e-5,
        "rope_theta": 100.0,
        "query_bias": True,
        "key_bias": False,
        "value_bias": True,
        "pos_embed_rescale": 2.0,
    }
    (folder / "config.json").write_text(json.dumps(hf_cfg))
    return folder


def _forward_tol(enc: torch.nn.Module, n_tokens: int) -> float:
    """Relative rounding estimate of one float32 encoder pass (``forward_rel_tol``): its Linear/conv/LayerNorm
    layers, and per block QKᵀ over the head size, the softmax sum and softmax·V over the tokens, and the float32
    RoPE tables' ε ≤ (10π + 2)u on each of q and k (≈ 68 roundings of a score)."""
    cfg = enc.config
    per_block = [cfg.embed_dim // cfg.num_heads, n_tokens, n_tokens, 68]
    return forward_rel_tol(enc, *(cfg.depth * per_block))


def reference_forward(sd: dict[str, torch.Tensor], cfg: DINOv3Config, x: torch.Tensor) -> torch.Tensor:
    """Naive DINOv3 forward in float64 on ImageNet-normalised images → all tokens after the final norm."""
    sd = {k: v.double() for k, v in sd.items()}
    x = x.double()
    b, _, height, width = x.shape
    p, c, heads = 16, cfg.embed_dim, cfg.num_heads
    hd = c // heads
    h, w = height // p, width // p
    patches = x.unfold(2, p, p).unfold(3, p, p).permute(0, 2, 3, 1, 4, 5).reshape(b, h * w, 3 * p * p)
    t = patches @ sd["patch_embed.proj.weight"].reshape(c, -1).T + sd["patch_embed.proj.bias"]
    tokens = torch.cat([sd["cls_token"].expand(b, 1, c), sd["storage_tokens"].expand(b, 4, c), t], dim=1)
    periods = sd["rope_embed.periods"]
    theta = torch.empty(h * w, hd // 2, dtype=torch.float64)
    for i in range(h):
        for j in range(w):
            yc, xc = 2 * (i + 0.5) / h - 1, 2 * (j + 0.5) / w - 1
            theta[i * w + j] = torch.cat([2 * math.pi * yc / periods, 2 * math.pi * xc / periods])
    rot = torch.polar(torch.ones_like(theta), theta)  # e^{iθ}

    def rope(z: torch.Tensor) -> torch.Tensor:  # [B, heads, N, hd], patches are the last h·w tokens
        pre, pat = z[:, :, : -h * w], z[:, :, -h * w :]
        zc = torch.complex(pat[..., : hd // 2], pat[..., hd // 2 :]) * rot
        return torch.cat([pre, torch.cat([zc.real, zc.imag], dim=-1)], dim=2)

    def ln(z: torch.Tensor, key: str) -> torch.Tensor:
        mu = z.mean(-1, keepdim=True)
        var = ((z - mu) ** 2).mean(-1, keepdim=True)
        return (z - mu) / torch.sqrt(var + 1e-5) * sd[key + ".weight"] + sd[key + ".bias"]

    n = tokens.shape[1]
    for i in range(cfg.depth):
        k = f"blocks.{i}."
        a = ln(tokens, k + "norm1")
        qkv = a @ sd[k + "attn.qkv.weight"].T + sd[k + "attn.qkv.bias"] * sd[k + "attn.qkv.bias_mask"]
        q, kk, v = (qkv[..., j * c : (j + 1) * c].reshape(b, n, heads, hd).transpose(1, 2) for j in range(3))
        q, kk = rope(q), rope(kk)
        att = torch.softmax(q @ kk.transpose(-1, -2) / math.sqrt(hd), dim=-1) @ v
        att = att.transpose(1, 2).reshape(b, n, c) @ sd[k + "attn.proj.weight"].T + sd[k + "attn.proj.bias"]
        tokens = tokens + sd[k + "ls1.gamma"] * att
        a = ln(tokens, k + "norm2")
        if cfg.ffn == "swiglu":
            g1 = a @ sd[k + "mlp.w1.weight"].T + sd[k + "mlp.w1.bias"]
            g2 = a @ sd[k + "mlp.w2.weight"].T + sd[k + "mlp.w2.bias"]
            m = (g1 * torch.sigmoid(g1) * g2) @ sd[k + "mlp.w3.weight"].T + sd[k + "mlp.w3.bias"]
        else:
            hid = a @ sd[k + "mlp.fc1.weight"].T + sd[k + "mlp.fc1.bias"]
            hid = 0.5 * hid * (1 + torch.erf(hid / math.sqrt(2)))
            m = hid @ sd[k + "mlp.fc2.weight"].T + sd[k + "mlp.fc2.bias"]
        tokens = tokens + sd[k + "ls2.gamma"] * m
    return ln(tokens, "norm")


IMAGENET_MEAN_T = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
IMAGENET_STD_T = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def random_images(b: int, h: int, w: int, seed: int = 1) -> torch.Tensor:
    """Images in macsplat's [-1, 1] convention. [B, 3, H, W]"""
    return torch.rand(b, 3, h, w, generator=torch.Generator().manual_seed(seed)) * 2 - 1


@pytest.fixture
def tiny_pth(tmp_path: Path) -> tuple[Path, dict[str, torch.Tensor]]:
    sd = random_official_state_dict(TINY)
    path = tmp_path / "dinov3_tiny.pth"
    torch.save(sd, path)
    return path, sd


# ------------------------------------------------------------------------------------------------
# Layout of the released variants (meta device: no memory)
# ------------------------------------------------------------------------------------------------

VARIANTS = {
    # preset: (C, depth, heads, hidden, ffn, number of keys, parameters in millions per the reference)
    "vits16": (384, 12, 6, 1536, "mlp", 188, 21.6),
    "vits16plus": (384, 12, 6, 1536, "swiglu", 212, 28.7),
    "vitb16": (768, 12, 12, 3072, "mlp", 188, 85.7),
    "vitl16": (1024, 24, 16, 4096, "mlp", 368, 303.2),
}


@pytest.mark.parametrize("name", list(VARIANTS))
def test_preset_keys_and_shapes_match_official_layout(name: str) -> None:
    c, depth, heads, hidden, ffn, n_keys, mparams = VARIANTS[name]
    with torch.device("meta"):
        enc = DINOv3Encoder(DINOv3Config.preset(name))
    got = {k: tuple(v.shape) for k, v in enc.state_dict().items()}
    assert got == official_spec(c, depth, heads, hidden, ffn)
    assert len(got) == n_keys
    # an exact count against the reference's figure, which is rounded to 0.1 M (± 0.05 M)
    assert sum(p.numel() for p in enc.parameters()) / 1e6 == pytest.approx(mparams, abs=0.05)


def test_vits16_has_188_keys() -> None:
    with torch.device("meta"):
        enc = DINOv3Encoder(DINOv3Config.preset("vits16"))
    assert len(enc.state_dict()) == 188
    assert enc.rope_embed.periods.shape == (16,)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_variant_inferred_from_shapes(name: str) -> None:
    with torch.device("meta"):
        sd = DINOv3Encoder(DINOv3Config.preset(name)).state_dict()
    assert infer_dinov3_config(sd) == DINOv3Config.preset(name)


def test_sat_vitl_inferred_from_local_cls_norm() -> None:
    with torch.device("meta"):
        sd = DINOv3Encoder(DINOv3Config.preset("vitl16")).state_dict()
        sd["local_cls_norm.weight"] = torch.empty(1024)
        sd["local_cls_norm.bias"] = torch.empty(1024)
        cfg = infer_dinov3_config(sd)
        assert cfg.untie_global_and_local_cls_norm and cfg.image_mean == SAT493M_MEAN
        assert set(DINOv3Encoder(cfg).state_dict()) == set(sd)


def test_tiny_config_inferred_from_random_state_dict() -> None:
    for cfg in (TINY, TINY_SWIGLU):
        inferred = infer_dinov3_config(random_official_state_dict(cfg))
        assert dataclasses.replace(inferred, name=cfg.name) == cfg


def test_infer_rejects_non_vit() -> None:
    with pytest.raises(DINOv3CheckpointError, match="cls_token") as e:
        infer_dinov3_config({"foo.weight": torch.zeros(3)})
    assert e.value.key == "cls_token"
    with pytest.raises(DINOv3CheckpointError, match="ConvNeXt"):
        infer_dinov3_config({"downsample_layers.0.0.weight": torch.zeros(96, 3, 4, 4)})


def stored_periods(head_dim: int, base: float, dtype: torch.dtype) -> torch.Tensor:
    """``rope_embed.periods`` as a checkpoint stores it: computed in float32, saved as ``dtype``."""
    i = torch.arange(head_dim // 4, dtype=torch.float32)
    return (base ** (2 * i / (head_dim // 2))).to(dtype)


def real_state_dict(name: str, periods: torch.Tensor, *, sat: bool = False) -> dict[str, torch.Tensor]:
    """A CPU (not meta) state dict of the named variant's shapes: zero-stride tensors, plus the given periods."""
    c, depth, heads, hidden, ffn, _, _ = VARIANTS[name]
    sd = {k: torch.zeros(()).expand(shape) for k, shape in official_spec(c, depth, heads, hidden, ffn).items()}
    if sat:
        sd["local_cls_norm.weight"] = torch.zeros(()).expand(c)
        sd["local_cls_norm.bias"] = torch.zeros(()).expand(c)
    sd["rope_embed.periods"] = periods
    return sd


# float32 periods, bfloat16 periods, and bfloat16 periods converted back to float32 (a converted file).
PERIOD_DTYPES = {
    "float32": lambda p: p,
    "bfloat16": lambda p: p.to(torch.bfloat16),
    "bf16-in-float32": lambda p: p.to(torch.bfloat16).float(),
}


@pytest.mark.parametrize("stored", list(PERIOD_DTYPES))
@pytest.mark.parametrize("name", list(VARIANTS))
def test_preset_recognised_from_real_periods(name: str, stored: str) -> None:
    periods = PERIOD_DTYPES[stored](stored_periods(64, 100.0, torch.float32))
    sd = real_state_dict(name, periods)
    assert sd["rope_embed.periods"].device.type == "cpu" and sd["cls_token"].device.type == "cpu"
    if stored != "float32":  # the old rule, periods[1] ** P, is far from 100 here (102.94)
        assert abs(float(periods[1].double() ** periods.numel()) - 100.0) > 1.0
    cfg = infer_dinov3_config(sd)
    assert cfg == DINOv3Config.preset(name)
    assert cfg.rope_base == 100.0 and cfg.image_mean == IMAGENET_MEAN


@pytest.mark.parametrize("stored", list(PERIOD_DTYPES))
def test_sat493m_vitl_recognised_from_real_periods(stored: str) -> None:
    periods = PERIOD_DTYPES[stored](stored_periods(64, 100.0, torch.float32))
    cfg = infer_dinov3_config(real_state_dict("vitl16", periods, sat=True))
    assert cfg.name == "vitl16-sat493m" and cfg.rope_base == 100.0
    assert cfg.image_mean == SAT493M_MEAN and cfg.image_std == SAT493M_STD
    assert cfg.untie_global_and_local_cls_norm
    assert dataclasses.replace(cfg, name="vitl16", untie_global_and_local_cls_norm=False, image_mean=IMAGENET_MEAN,
                               image_std=IMAGENET_STD) == DINOv3Config.preset("vitl16")  # fmt: skip


@pytest.mark.parametrize("stored", list(PERIOD_DTYPES))
@pytest.mark.parametrize("head_dim", [32, 64, 128])
def test_rope_base_100_from_stored_periods(head_dim: int, stored: str) -> None:
    periods = PERIOD_DTYPES[stored](stored_periods(head_dim, 100.0, torch.float32))
    assert rope_base_from_periods(periods) == 100.0


@pytest.mark.parametrize("stored", list(PERIOD_DTYPES))
@pytest.mark.parametrize("base", [101.0, 200.0, 10000.0])
def test_other_rope_base_is_custom(base: float, stored: str) -> None:
    periods = PERIOD_DTYPES[stored](stored_periods(64, base, torch.float32))
    for sat in (False, True):
        cfg = infer_dinov3_config(real_state_dict("vitl16", periods, sat=sat))
        assert cfg.name.startswith("custom-1024d-24x16h-mlp4096-rope"), cfg.name
        assert cfg.image_mean == IMAGENET_MEAN  # not the SAT-493M normalisation: not that model
        # The base is the least-squares slope of log pᵢ = (i/P)·log base, printed to 4 significant digits. Periods
        # off by ≤ u relative (u of the stored dtype, + 5u32 of the float32 pow) move log base by
        # ≤ u·Σeᵢ/Σeᵢ² = u·3P/(2P − 1); the 4-digit rounding adds ≤ 5e-4 relative. For float32 periods the fit is
        # within 1e-6 of a 4-digit base, so the rounding returns it exactly.
        if stored == "float32":
            assert cfg.rope_base == base
        else:
            p = 64 // 4
            rel = 3 * p / (2 * p - 1) * (unit_roundoff(torch.bfloat16) + 5 * U32) + 5e-4
            assert cfg.rope_base == pytest.approx(base, rel=rel, abs=0)
        assert cfg.untie_global_and_local_cls_norm == sat
        with torch.device("meta"):
            assert set(DINOv3Encoder(cfg).state_dict()) == set(real_state_dict("vitl16", periods, sat=sat))


def test_tiny_bf16_periods_are_not_a_custom_rope() -> None:
    sd = random_official_state_dict(TINY)
    sd["rope_embed.periods"] = sd["rope_embed.periods"].to(torch.bfloat16)
    cfg = infer_dinov3_config(sd)
    assert cfg.rope_base == 100.0 and cfg.name == "custom-64d-2x2h-mlp128"


@pytest.mark.parametrize("bad", [[1.0, 0.0, 3.0, 4.0], [1.0, -2.0, 3.0, 4.0], [1.0, float("nan"), 3.0, 4.0]])
def test_nonpositive_periods_rejected(bad: list[float]) -> None:
    sd = random_official_state_dict(dataclasses.replace(TINY, num_heads=4))
    sd["rope_embed.periods"] = torch.tensor(bad[:4])
    with pytest.raises(DINOv3CheckpointError, match="positive and finite") as e:
        infer_dinov3_config(sd)
    assert e.value.key == "rope_embed.periods"


# ------------------------------------------------------------------------------------------------
# RoPE
# ------------------------------------------------------------------------------------------------


def test_rope_periods_vits16() -> None:
    p = rope_periods(64, 100.0)
    assert p.shape == (16,)
    assert p[0].item() == 1.0
    assert p[-1].item() == pytest.approx(74.99, abs=5e-3)  # 100^(15/16) = 74.989…; the reference gives 2 decimals
    assert torch.all(p[1:] > p[:-1])


def test_rope_tables_hand_computed() -> None:
    periods = torch.tensor([1.0, 10.0])  # head_dim 8
    sin, cos = rope_sin_cos(periods, 2, 2)
    assert sin.shape == cos.shape == (4, 8)
    pi = math.pi
    # token 1 = row 0, column 1: y = 2·0.25 − 1 = −0.5, x = +0.5; y frequencies first, then x, tiled twice.
    expected = torch.tensor([-pi, -pi / 10, pi, pi / 10] * 2)
    # float32: the coordinates are exact here; θ = fl(2π)·c/p is 3 roundings (3u|θ|), the test's θ one (u|θ|); sin
    # and cos to 1 ulp each side (2·2u): |Δ| ≤ 4u·|θ| + 4u
    tol = U32 * (4 * math.pi + 4)
    torch.testing.assert_close(sin[1], torch.sin(expected), rtol=0, atol=tol)
    torch.testing.assert_close(cos[1], torch.cos(expected), rtol=0, atol=tol)
    # "separate" normalisation on a 1×3 grid: y = 0, x ∈ {−2/3, 0, 2/3}.
    sin, cos = rope_sin_cos(periods, 1, 3)
    angles_x = torch.tensor([-2 / 3, 0.0, 2 / 3])[:, None] * 2 * pi / periods
    # x = 2·(j + 0.5)/3 − 1 is now ≤ 2u off (the /3 and the cancelling − 1), i.e. ≤ 2π·2u in θ (p ≥ 1); the test's
    # −2/3 and 2π/p ≤ 3u|θ|; |θ| ≤ 4π/3: |Δ| ≤ (4π + 4·4π/3 + 4)u
    tol_x = U32 * (4 * math.pi + 16 * math.pi / 3 + 4)
    torch.testing.assert_close(sin[:, 2:4], torch.sin(angles_x), rtol=0, atol=tol_x)
    # y = 2·0.5 − 1 = 0 exactly, and sin 0 = 0 for any sin with a relative error bound
    assert torch.equal(sin[:, 0:2], torch.zeros(3, 2))


def test_rope_relative_position_property() -> None:
    """After rotation, q·k depends only on the grid offset between the two tokens."""
    h, w, hd = 4, 5, 16
    sin, cos = rope_sin_cos(rope_periods(hd, 100.0), h, w)
    g = torch.Generator().manual_seed(3)
    q = torch.randn(hd, generator=g, dtype=torch.float64).expand(h * w, hd)
    k = torch.randn(hd, generator=g, dtype=torch.float64).expand(h * w, hd)
    qr, kr = apply_rope(q, sin.double(), cos.double()), apply_rope(k, sin.double(), cos.double())
    # The float32 tables: c, s within 1 ulp (2u32 relative) of cos, sin of the same float32 θ, so c² + s² = 1 ± 4u32
    # and each pair's length moves by ≤ 2u32; the float64 arithmetic and norms add γ₃₂(f64)
    torch.testing.assert_close(qr.norm(dim=-1), q.norm(dim=-1), rtol=2 * U32 + gamma(32, torch.float64), atol=0)
    dots = qr @ kr.T  # [hw, hw]
    by_offset: dict[tuple[int, int], list[float]] = {}
    for a in range(h * w):
        for b in range(h * w):
            by_offset.setdefault((b // w - a // w, b % w - a % w), []).append(float(dots[a, b]))
    # Each table entry is off the exact cos/sin of the exact angle by ε ≤ δθ + 2u32, δθ ≤ 2π·2u (the coordinate, p ≥ 1)
    # + 3u·2π (the float32 product and quotient, |θ| ≤ 2π): ε ≤ (10π + 2)u32. A rotated pair moves by ≤ ε·‖pair‖₁, so a
    # score by ≤ 4ε·S, S = Σ over pairs of ‖q pair‖₁‖k pair‖₁; two scores of one offset differ by ≤ 8εS (+ float64)
    eps = (10 * math.pi + 2) * U32
    pq, pk = q[0].abs(), k[0].abs()
    s_pairs = float(((pq[: hd // 2] + pq[hd // 2 :]) * (pk[: hd // 2] + pk[hd // 2 :])).sum())
    spread = 8 * eps * s_pairs + 2 * gamma(hd, torch.float64) * s_pairs
    for vals in by_offset.values():
        assert max(vals) - min(vals) <= spread
    means = {off: sum(v) / len(v) for off, v in by_offset.items()}
    assert abs(means[(0, 1)] - means[(0, 0)]) > 1e-3  # the rotation does depend on the offset
    assert abs(means[(1, 0)] - means[(0, 1)]) > 1e-3


# ------------------------------------------------------------------------------------------------
# Forward
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cfg", [TINY, TINY_SWIGLU], ids=["mlp", "swiglu"])
def test_forward_matches_naive_reference(cfg: DINOv3Config) -> None:
    sd = random_official_state_dict(cfg, seed=5)
    enc = DINOv3Encoder(cfg)
    enc.load_state_dict(sd, strict=True)
    img = random_images(2, 48, 80)
    out = enc.encode(img)
    x = ((img * 0.5 + 0.5) - IMAGENET_MEAN_T) / IMAGENET_STD_T
    ref = reference_forward(sd, cfg, x)  # [B, 1+4+hw, C] float64
    assert out.patch.shape == (2, 3, 5, cfg.embed_dim)
    # (c) float32 against the float64 reference: within _forward_tol relative to the largest value (measured ≤ 122u)
    tol = _forward_tol(enc, n_tokens=1 + 4 + 3 * 5)
    assert max_rel_err(out.cls.double(), ref[:, 0].double()) <= tol
    assert max_rel_err(out.storage.double(), ref[:, 1:5].double()) <= tol
    assert max_rel_err(out.patch.double(), ref[:, 5:].reshape(2, 3, 5, -1).double()) <= tol
    # The weights were chosen so that RoPE matters: dropping it changes the output.
    no_rope = reference_forward({**sd, "rope_embed.periods": torch.full_like(sd["rope_embed.periods"], 1e9)}, cfg, x)
    assert (no_rope[:, 5:].float() - ref[:, 5:]).abs().max() > 1e-2


@pytest.mark.parametrize(("height", "width"), [(64, 32), (32, 80), (48, 48), (16, 112)])
def test_output_shape_any_multiple_of_16(height: int, width: int) -> None:
    enc = DINOv3Encoder(TINY)
    out = enc(random_images(2, height, width))
    assert out.shape == (2, height // 16, width // 16, TINY.embed_dim)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("shape", [(1, 3, 40, 48), (1, 1, 32, 32), (3, 32, 32), (1, 4, 32, 32)])
def test_bad_image_shape_raises(shape: tuple[int, ...]) -> None:
    with pytest.raises(ShapeError):
        DINOv3Encoder(TINY)(torch.zeros(shape))


def test_imagenet_renormalisation() -> None:
    enc = DINOv3Encoder(TINY)
    ones = torch.ones(1, 3, 2, 2)
    # (a) ±1·0.5 + 0.5 is 0 or 1 exactly, then the same subtraction and division as the test's
    assert torch.equal(enc.renormalize(-ones), (-IMAGENET_MEAN_T / IMAGENET_STD_T).expand(1, 3, 2, 2))
    assert torch.equal(enc.renormalize(ones), ((1 - IMAGENET_MEAN_T) / IMAGENET_STD_T).expand(1, 3, 2, 2))
    img = random_images(2, 32, 48)
    manual = ((img + 1) / 2 - IMAGENET_MEAN_T) / IMAGENET_STD_T
    # (a) fl(x·0.5 + 0.5) = fl(x + 1)/2: halving is exact and commutes with rounding; the rest is the same operations
    assert torch.equal(enc.renormalize(img), manual)
    # (a) so the encoder then runs the same kernels on the same numbers
    assert torch.equal(enc(img), enc.encode_normalized(manual).patch)
    # Feeding [-1, 1] images straight to the normalised entry point gives something else.
    assert (enc.encode_normalized(img).patch - enc(img)).abs().max() > 1e-3
    sat = DINOv3Encoder(dataclasses.replace(TINY, image_mean=SAT493M_MEAN))
    assert not torch.allclose(sat.renormalize(img), manual)


def test_stays_in_eval_mode() -> None:
    enc = DINOv3Encoder(TINY)
    enc.load_state_dict(random_official_state_dict(TINY), strict=True)
    img = random_images(1, 32, 32)
    before = enc(img)
    assert enc.train() is enc
    assert not enc.training and not any(m.training for m in enc.modules())
    parent = nn.ModuleDict({"enc": enc, "head": nn.Linear(2, 2)})
    parent.train()
    assert parent.training and parent["head"].training
    assert not any(m.training for m in enc.modules())
    assert torch.equal(enc(img), before)


def test_frozen_no_grads(tiny_pth: tuple[Path, dict[str, torch.Tensor]]) -> None:
    for enc in (DINOv3Encoder(TINY), load_dinov3(tiny_pth[0])):
        assert all(not p.requires_grad for p in enc.parameters())
        out = enc(random_images(1, 32, 32))
        assert not out.requires_grad and out.grad_fn is None


# ------------------------------------------------------------------------------------------------
# Loading
# ------------------------------------------------------------------------------------------------


def test_load_official_pth_strict(tiny_pth: tuple[Path, dict[str, torch.Tensor]]) -> None:
    path, sd = tiny_pth
    for cfg in (TINY, None):
        enc = load_dinov3(path, cfg)
        loaded = enc.state_dict()
        assert set(loaded) == set(sd)
        assert all(torch.equal(loaded[k], sd[k]) for k in sd)
        assert not enc.training and all(not p.requires_grad for p in enc.parameters())
    img = random_images(1, 32, 64)
    x = ((img * 0.5 + 0.5) - IMAGENET_MEAN_T) / IMAGENET_STD_T
    ref = reference_forward(sd, TINY, x)[:, 5:].reshape(1, 2, 4, -1)
    assert max_rel_err(enc(img).double(), ref) <= _forward_tol(enc, n_tokens=1 + 4 + 2 * 4)  # (c), as above


@pytest.mark.parametrize("cfg", [TINY, TINY_SWIGLU], ids=["mlp", "swiglu"])
def test_load_hf_folder_matches_official(tmp_path: Path, cfg: DINOv3Config) -> None:
    sd = random_official_state_dict(cfg, seed=7)
    official = tmp_path / "official.pth"
    torch.save(sd, official)
    folder = write_hf_folder(tmp_path / "hf", sd, cfg)
    enc_hf = load_dinov3(folder)
    assert dataclasses.replace(enc_hf.config, name=cfg.name) == cfg
    img = random_images(2, 48, 32)
    # (a) the conversion only moves numbers (checked bitwise below): the same module, weights and input
    assert torch.equal(enc_hf(img), load_dinov3(official)(img))


def test_hf_config_checked(tmp_path: Path) -> None:
    folder = write_hf_folder(tmp_path / "hf", random_official_state_dict(TINY), TINY)
    hf_cfg = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**hf_cfg, "hidden_act": "relu"}))
    with pytest.raises(DINOv3CheckpointError, match="hidden_act 'relu'"):
        load_dinov3(folder)
    (folder / "config.json").write_text(json.dumps({**hf_cfg, "hidden_size": 96}))
    with pytest.raises(DINOv3CheckpointError, match="hidden_size 96"):
        load_dinov3(folder)


def test_hf_mapping_round_trip_and_model_prefix(tmp_path: Path) -> None:
    sd = random_official_state_dict(TINY)
    for prefix in ("", "model."):  # hub files, transformers' in-memory names
        back = hf_to_official(official_to_hf(sd, prefix=prefix))
        expected = {k: v for k, v in sd.items() if k != "rope_embed.periods"}
        assert set(back) == set(expected)
        for k, v in expected.items():
            if k.endswith("attn.qkv.bias"):  # HF has no key bias: it comes back as zeros, masked anyway
                c = v.shape[0] // 3
                assert torch.equal(back[k][c : 2 * c], torch.zeros(c))
                assert torch.equal(back[k][:c], v[:c]) and torch.equal(back[k][2 * c :], v[2 * c :])
            else:
                assert torch.equal(back[k], v), k
    # A single .safetensors file with in-memory HF names loads too (heads from the released-width table
    # would be wrong for the tiny width, so pass the config).
    single = tmp_path / "tiny_hf.safetensors"
    write_safetensors(single, official_to_hf(sd, prefix="model."))
    enc = load_dinov3(single, TINY)
    # HF files have no periods: the encoder computes base^(2i/(D/2)) in float32, the test's file in float64 then
    # rounds: pow to 2 ulp (4u) and the rounding (u), of values ≤ 100^(7/8)
    torch.testing.assert_close(enc.rope_embed.periods, sd["rope_embed.periods"], rtol=5 * U32, atol=0)


def test_hf_unknown_key_is_named() -> None:
    hf = official_to_hf(random_official_state_dict(TINY))
    hf["layer.0.attention.extra.weight"] = torch.zeros(2, 3)
    with pytest.raises(DINOv3CheckpointError, match=r"layer\.0\.attention\.extra\.weight") as e:
        hf_to_official(hf)
    assert e.value.file_shape == (2, 3)


def test_mismatched_shape_names_first_bad_key(tmp_path: Path) -> None:
    sd = random_official_state_dict(TINY)
    sd["blocks.1.attn.proj.weight"] = torch.zeros(64, 32)
    sd["blocks.1.mlp.fc2.weight"] = torch.zeros(64, 7)
    path = tmp_path / "bad.pth"
    torch.save(sd, path)
    for cfg in (TINY, None):
        with pytest.raises(DINOv3CheckpointError) as e:
            load_dinov3(path, cfg)
        err = e.value
        assert isinstance(err, InputError) and err.exit_code == 2
        assert err.key == "blocks.1.attn.proj.weight"
        assert err.file_shape == (64, 32) and err.expected_shape == (64, 64)
        assert "'blocks.1.attn.proj.weight'" in str(err) and "[64, 32]" in str(err) and "[64, 64]" in str(err)


def test_wrong_variant_names_first_key(tiny_pth: tuple[Path, dict[str, torch.Tensor]]) -> None:
    with pytest.raises(DINOv3CheckpointError, match=r"'cls_token' has shape \[1, 1, 64\].*\[1, 1, 384\]") as e:
        load_dinov3(tiny_pth[0], DINOv3Config.preset("vits16"))
    assert e.value.key == "cls_token"


def test_missing_and_unexpected_keys(tmp_path: Path) -> None:
    sd = random_official_state_dict(TINY)
    missing = {k: v for k, v in sd.items() if k != "blocks.0.ls2.gamma"}
    torch.save(missing, tmp_path / "missing.pth")
    with pytest.raises(DINOv3CheckpointError, match="missing") as e:
        load_dinov3(tmp_path / "missing.pth", TINY)
    assert e.value.key == "blocks.0.ls2.gamma" and e.value.file_shape is None
    torch.save({**sd, "head.weight": torch.zeros(5, 64)}, tmp_path / "extra.pth")
    with pytest.raises(DINOv3CheckpointError, match="unexpected key 'head.weight'") as e:
        load_dinov3(tmp_path / "extra.pth")
    assert e.value.file_shape == (5, 64)


def test_missing_file_says_where_to_get_weights(tmp_path: Path) -> None:
    path = tmp_path / "dinov3_vits16_pretrain_lvd1689m-08c60483.pth"
    with pytest.raises(DINOv3WeightsNotFoundError) as e:
        load_dinov3(path)
    msg = str(e.value)
    assert str(path) in msg and "ai.meta.com" in msg and "Hugging Face" in msg and "licence" in msg
    assert isinstance(e.value, InputError) and isinstance(e.value, FileNotFoundError)
    folder = tmp_path / "hf"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    with pytest.raises(DINOv3WeightsNotFoundError, match="model.safetensors"):
        load_dinov3(folder)


def test_unreadable_files(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"this is not a checkpoint")
    with pytest.raises(DINOv3CheckpointError, match="not a readable"):
        load_dinov3(garbage)
    wrapped = tmp_path / "wrapped.pth"
    torch.save({"model": random_official_state_dict(TINY), "epoch": 3}, wrapped)
    with pytest.raises(DINOv3CheckpointError, match="plain state dict"):
        load_dinov3(wrapped)
    truncated = tmp_path / "t.safetensors"
    write_safetensors(truncated, {"cls_token": torch.zeros(1, 1, 64)})
    truncated.write_bytes(truncated.read_bytes()[:-8])
    with pytest.raises(DINOv3CheckpointError, match="inconsistent offsets"):
        read_safetensors(truncated)


def test_sha256_logged_at_debug(
    tiny_pth: tuple[Path, dict[str, torch.Tensor]], caplog: pytest.LogCaptureFixture
) -> None:
    path = tiny_pth[0]
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    with caplog.at_level(logging.INFO, logger="macsplat_cli.neural.dinov3"):
        load_dinov3(path)
    assert digest not in caplog.text  # hashing a 1 GB file only when asked
    with caplog.at_level(logging.DEBUG, logger="macsplat_cli.neural.dinov3"):
        load_dinov3(path)
    assert digest in caplog.text


def test_safetensors_reader_matches_package(tmp_path: Path) -> None:
    st = pytest.importorskip("safetensors.torch")
    g = torch.Generator().manual_seed(0)
    tensors = {
        "a": torch.randn(3, 5, generator=g),
        "b": torch.randn(7, generator=g).to(torch.bfloat16),
        "c": torch.randn(2, 3, generator=g).half(),
        "d": torch.arange(5, dtype=torch.int64),
        "e": torch.zeros(0, 4),
    }
    path = tmp_path / "x.safetensors"
    st.save_file(tensors, str(path))
    got = read_safetensors(path)
    assert set(got) == set(tensors)
    for k, v in tensors.items():
        assert got[k].dtype == v.dtype and torch.equal(got[k], v), k
    ours = tmp_path / "ours.safetensors"
    write_safetensors(ours, {k: v for k, v in tensors.items() if k != "e"})
    back = st.load_file(str(ours))
    assert all(torch.equal(back[k], tensors[k]) for k in back)


def test_bf16_checkpoint_loads_as_float32(tmp_path: Path) -> None:
    sd = random_official_state_dict(TINY)
    path = tmp_path / "bf16.pth"
    torch.save({k: v.to(torch.bfloat16) for k, v in sd.items()}, path)
    enc = load_dinov3(path)
    assert enc.cls_token.dtype == torch.float32 and enc.rope_embed.periods.dtype == torch.float32
    assert enc.config.rope_base == 100.0 and enc.config.name == "custom-64d-2x2h-mlp128"  # bf16 periods, base 100
    torch.testing.assert_close(enc.cls_token, sd["cls_token"].to(torch.bfloat16).float(), rtol=0, atol=0)
    full = DINOv3Encoder(TINY)
    full.load_state_dict(sd, strict=True)
    img = random_images(1, 32, 32)
    assert F.cosine_similarity(enc(img).flatten(), full(img).flatten(), dim=0).item() > 0.99
