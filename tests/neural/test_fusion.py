"""Tests for Residual Semantic Fusion (DINOv3 features → residual on the matching descriptors)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from macsplat_cli.errors import InputError, ShapeError
from macsplat_cli.neural.dinov3 import DINOv3Config, DINOv3Encoder
from macsplat_cli.neural.fusion import (
    FusionCheckpointError,
    FusionConfig,
    ResidualSemanticFusion,
    fuse_descriptors,
    load_fusion,
    save_fusion,
)

from support.numerics import gamma, unit_roundoff

TINY = DINOv3Config.preset("tiny")  # C = 64
U32 = unit_roundoff(torch.float32)
# Renormalised output f'·‖f‖/‖f'‖ of unit f (F.normalize: ‖f‖ = 1 ± (γ₂₄/2 + 2u)): the two norms (γ₂₄/2 + u each),
# the quotient and the product (2u), and a test's norm (γ₂₄/2 + u): |‖out‖ − 1| ≤ 2γ₂₄ + 6u
UNIT_LEN = 2 * gamma(24, torch.float32) + 6 * U32
CFG = FusionConfig(desc_dim=24, dino_dim=64, hidden_dim=32, depth=2)


def unit_descriptors(b: int, h: int, w: int, d: int = 24, seed: int = 0) -> torch.Tensor:
    """L2-normalised descriptors, as MASt3R outputs them. [B, H, W, D]"""
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(b, h, w, d, generator=g), dim=-1)


def dino_features(b: int, h: int, w: int, c: int = 64, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, h, w, c, generator=g)


def trained_like(cfg: FusionConfig = CFG, seed: int = 2) -> ResidualSemanticFusion:
    """A module whose last layer is no longer zero (as after training)."""
    torch.manual_seed(seed)
    m = ResidualSemanticFusion(cfg)
    with torch.no_grad():
        m.layers[-1].weight.normal_(0.0, 0.3)
        m.layers[-1].bias.normal_(0.0, 0.1)
    return m


def test_state_dict_keys_and_zero_init() -> None:
    m = ResidualSemanticFusion(CFG)
    shapes = {k: tuple(v.shape) for k, v in m.state_dict().items()}
    assert shapes == {
        "proj.weight": (24, 64),
        "proj.bias": (24,),
        "layers.0.weight": (32, 48),
        "layers.0.bias": (32,),
        "layers.1.weight": (24, 32),
        "layers.1.bias": (24,),
    }
    assert torch.count_nonzero(m.layers[-1].weight) == 0 and torch.count_nonzero(m.layers[-1].bias) == 0
    assert torch.count_nonzero(m.layers[0].weight) > 0 and torch.count_nonzero(m.proj.weight) > 0
    deep = ResidualSemanticFusion(FusionConfig(dino_dim=64, hidden_dim=16, depth=3))
    assert [tuple(layer.weight.shape) for layer in deep.layers] == [(16, 48), (16, 16), (24, 16)]
    with pytest.raises(ValueError):
        FusionConfig(depth=1)


@pytest.mark.parametrize("renormalize", [True, False])
def test_untrained_leaves_descriptors_exactly_unchanged(renormalize: bool) -> None:
    m = ResidualSemanticFusion(FusionConfig(dino_dim=64, renormalize=renormalize))
    dino = dino_features(2, 2, 3)
    for desc in (unit_descriptors(2, 32, 48), 3.0 * torch.randn(2, 32, 48, 24)):
        out = m(desc, dino)
        assert torch.equal(out, desc)


def test_renormalised_output_keeps_descriptor_length() -> None:
    desc = unit_descriptors(1, 16, 16)
    m = trained_like()
    out = m(desc, dino_features(1, 1, 1))
    assert (out - desc).abs().max() > 1e-2
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(1, 16, 16), rtol=0, atol=UNIT_LEN)
    raw = ResidualSemanticFusion(FusionConfig(dino_dim=64, hidden_dim=32, renormalize=False))
    raw.load_state_dict(m.state_dict())
    plain = raw(desc, dino_features(1, 1, 1))
    assert (plain.norm(dim=-1) - 1).abs().max() > 1e-3  # without re-normalisation the length drifts
    # (b) plain·‖f‖/‖plain‖ vs plain/‖plain‖: ‖f‖ is 1 up to γ₂₄ + 3u, and each side's other roundings (≤ UNIT_LEN)
    torch.testing.assert_close(out, F.normalize(plain, dim=-1), rtol=0, atol=UNIT_LEN)


def test_zero_descriptor_is_safe() -> None:
    desc = unit_descriptors(1, 4, 4)
    desc[0, 1, 2] = 0.0
    desc.requires_grad_(True)
    m = trained_like()
    out = m(desc, dino_features(1, 1, 1))
    assert torch.isfinite(out).all() and torch.equal(out[0, 1, 2], torch.zeros(24))
    out.sum().backward()
    assert torch.isfinite(desc.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in m.parameters())


def test_one_optimiser_step_changes_descriptors() -> None:
    m = ResidualSemanticFusion(CFG)
    desc, dino = unit_descriptors(2, 16, 16), dino_features(2, 1, 1)
    target = unit_descriptors(2, 16, 16, seed=9)
    opt = torch.optim.SGD(m.parameters(), lr=0.5)
    loss = -(m(desc, dino) * target).sum()
    loss.backward()
    assert m.layers[-1].weight.grad.abs().max() > 0
    opt.step()
    opt.zero_grad()
    out = m(desc, dino)
    assert (out - desc).abs().max() > 1e-3
    assert -(out * target).sum() < loss  # the step moved towards the target
    # After the first step the last layer is non-zero, so every fusion parameter gets a gradient.
    (-(out * target).sum()).backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, name


def test_gradients_reach_fusion_not_encoder() -> None:
    enc = DINOv3Encoder(TINY)
    m = trained_like()
    image = torch.rand(1, 3, 32, 48) * 2 - 1
    desc = unit_descriptors(1, 32, 48).requires_grad_(True)
    result = fuse_descriptors(desc, image, fusion=m, encoder=enc)
    assert result.applied
    result.desc.square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().max() > 0 for p in m.parameters())
    assert desc.grad is not None
    assert all(p.grad is None and not p.requires_grad for p in enc.parameters())


def test_gradcheck_float64() -> None:
    cfg = FusionConfig(desc_dim=4, dino_dim=5, hidden_dim=6, depth=3)
    m = trained_like(cfg).double()
    desc = F.normalize(torch.randn(1, 3, 4, 4, dtype=torch.float64), dim=-1).requires_grad_(True)
    dino = torch.randn(1, 2, 2, 5, dtype=torch.float64, requires_grad=True)
    # float64: central differences with eps = 1e-6 err by O(eps²) ≈ 1e-12 (truncation) + u/eps ≈ 1e-10 (rounding)
    # relative to O(1) values, far inside atol/rtol; a wrong gradient term is off by O(1)
    assert torch.autograd.gradcheck(m, (desc, dino), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


# ------------------------------------------------------------------------------------------------
# Resizing the DINO grid to the descriptor grid
# ------------------------------------------------------------------------------------------------


def identity_projection(m: ResidualSemanticFusion) -> None:
    with torch.no_grad():
        m.proj.weight.zero_()
        m.proj.weight[:, :24] = torch.eye(24)
        m.proj.bias.zero_()


def test_bilinear_resize_aligns_patch_centres() -> None:
    """16-px DINO patches → full-resolution descriptors: patch (i, j) is centred at pixel (16i + 7.5, 16j + 7.5)."""
    m = ResidualSemanticFusion(CFG)
    identity_projection(m)
    h, w = 3, 4
    i = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w)
    j = torch.arange(w, dtype=torch.float32)[None, :].expand(h, w)
    dino = torch.zeros(1, h, w, 64)
    dino[0, :, :, 0] = (i + 0.5) * 16  # the y pixel coordinate of the patch centre (pixel-edge origin)
    dino[0, :, :, 1] = (j + 0.5) * 16
    dino[0, :, :, 2] = 5.0  # a constant field stays constant
    p = m.project_dino(dino, (16 * h, 16 * w))
    assert p.shape == (1, 48, 64, 24)
    y = torch.arange(48, dtype=torch.float32)[:, None] + 0.5  # pixel centres
    x = torch.arange(64, dtype=torch.float32)[None, :] + 0.5
    inner = (slice(8, 40), slice(8, 56))  # between the outermost patch centres (bilinear clamps beyond them)
    # float32: the identity projection is exact (products by 0 and 1, sums with zeros); the source coordinate
    # (dst + 0.5)·(in/out) − 0.5 is ≤ 2 roundings of values ≤ 4 input pixels (16 output px each, and the ramp's
    # slope is 1 per output px: ≤ 16·2u·4), the blend 3 roundings of values ≤ 56
    tol = U32 * (16 * 2 * 4 + 3 * 56)
    torch.testing.assert_close(p[0, :, :, 0][inner], y.expand(48, 64)[inner], rtol=0, atol=tol)
    torch.testing.assert_close(p[0, :, :, 1][inner], x.expand(48, 64)[inner], rtol=0, atol=tol)
    # a blend of equal values: ≤ 3 roundings of 5
    torch.testing.assert_close(p[0, :, :, 2], torch.full((48, 64), 5.0), rtol=0, atol=3 * U32 * 5.0)
    assert p[0, 0, 0, 0] == 8.0 and p[0, -1, -1, 1] == 56.0  # clamped at the border


def test_project_then_resize_equals_resize_then_project() -> None:
    m = ResidualSemanticFusion(CFG)
    dino = dino_features(2, 3, 5)
    resized = F.interpolate(dino.permute(0, 3, 1, 2), size=(40, 72), mode="bilinear", align_corners=False)
    # (b) two orders of two linear maps: the 64-term projection (γ₆₄ of Σ|W||x| + |b|) and the 4-term convex blend
    # (γ₃ of the largest input); each order within (γ₆₄ + γ₃)·S, S = the largest Σ|W||x| + |b|
    s_abs = float((dino.abs().amax(dim=(1, 2)) @ m.proj.weight.detach().abs().T + m.proj.bias.detach().abs()).max())
    tol = 2 * (gamma(64, torch.float32) + gamma(3, torch.float32)) * s_abs
    torch.testing.assert_close(m.project_dino(dino, (40, 72)), m.proj(resized.permute(0, 2, 3, 1)), rtol=0, atol=tol)


def test_same_grid_needs_no_resize() -> None:
    m = ResidualSemanticFusion(CFG)
    dino = dino_features(1, 4, 6)
    assert torch.equal(m.project_dino(dino, (4, 6)), m.proj(dino))


def test_descriptor_grid_coarser_than_dino_grid() -> None:
    m = trained_like()
    out = m(unit_descriptors(1, 2, 3), dino_features(1, 8, 12))
    assert out.shape == (1, 2, 3, 24) and torch.isfinite(out).all()


# ------------------------------------------------------------------------------------------------
# fuse_descriptors and boundary checks
# ------------------------------------------------------------------------------------------------


def test_skipped_without_encoder(caplog: pytest.LogCaptureFixture) -> None:
    desc = unit_descriptors(1, 32, 32)
    image = torch.zeros(1, 3, 32, 32)
    with caplog.at_level(logging.DEBUG, logger="macsplat_cli.neural.fusion"):
        result = fuse_descriptors(desc, image, fusion=trained_like(), encoder=None)
    assert result.desc is desc and not result.applied
    assert "skipped" in result.report and "DINOv3" in result.report and "skipped" in caplog.text
    result = fuse_descriptors(desc, image, fusion=None, encoder=DINOv3Encoder(TINY))
    assert result.desc is desc and not result.applied and "fusion weights" in result.report


def test_fuse_with_untrained_module_is_identity_and_reports() -> None:
    enc = DINOv3Encoder(TINY)
    desc = unit_descriptors(2, 48, 32)
    result = fuse_descriptors(desc, torch.rand(2, 3, 48, 32) * 2 - 1, fusion=ResidualSemanticFusion(CFG), encoder=enc)
    assert result.applied and torch.equal(result.desc, desc)
    assert "applied" in result.report and "3×2×64" in result.report and "48×32×24" in result.report


def test_shape_errors() -> None:
    m = ResidualSemanticFusion(CFG)
    with pytest.raises(ShapeError, match="descriptors"):
        m(torch.zeros(1, 8, 8, 16), dino_features(1, 1, 1))
    with pytest.raises(ShapeError, match="DINOv3 features"):
        m(unit_descriptors(1, 8, 8), torch.zeros(1, 1, 1, 32))
    with pytest.raises(ShapeError, match="DINOv3 features"):
        m(unit_descriptors(2, 8, 8), dino_features(1, 1, 1))
    other = DINOv3Encoder(DINOv3Config("w32", embed_dim=32, depth=1, num_heads=1, ffn="mlp", ffn_hidden_dim=32))
    with pytest.raises(ShapeError, match="dino_dim"):
        fuse_descriptors(unit_descriptors(1, 16, 16), torch.zeros(1, 3, 16, 16), fusion=m, encoder=other)
    with pytest.raises(ShapeError, match="image"):
        fuse_descriptors(unit_descriptors(1, 16, 16), torch.zeros(2, 3, 16, 16), fusion=m, encoder=DINOv3Encoder(TINY))


# ------------------------------------------------------------------------------------------------
# Saving and loading our own weights
# ------------------------------------------------------------------------------------------------


def test_save_load_round_trip(tmp_path: Path) -> None:
    cfg = FusionConfig(desc_dim=24, dino_dim=64, hidden_dim=16, depth=3, renormalize=False)
    m = trained_like(cfg)
    path = save_fusion(m, tmp_path / "sub" / "fusion.pth")
    back = load_fusion(path)
    assert back.config == cfg
    assert all(torch.equal(back.state_dict()[k], v) for k, v in m.state_dict().items())
    desc, dino = unit_descriptors(1, 8, 8), dino_features(1, 2, 2)
    assert torch.equal(back(desc, dino), m(desc, dino))


def test_load_errors(tmp_path: Path) -> None:
    with pytest.raises(FusionCheckpointError, match="not found") as e:
        load_fusion(tmp_path / "nope.pth")
    assert isinstance(e.value, InputError)
    torch.save({"proj.weight": torch.zeros(2, 2)}, tmp_path / "plain.pth")
    with pytest.raises(FusionCheckpointError, match="not a macsplat fusion file"):
        load_fusion(tmp_path / "plain.pth")
    (tmp_path / "garbage.pth").write_bytes(b"garbage")
    with pytest.raises(FusionCheckpointError, match="not a readable"):
        load_fusion(tmp_path / "garbage.pth")
    save_fusion(ResidualSemanticFusion(CFG), tmp_path / "f.pth")
    obj = torch.load(tmp_path / "f.pth", weights_only=True)
    obj["state_dict"]["layers.0.weight"] = torch.zeros(32, 40)
    torch.save(obj, tmp_path / "bad.pth")
    with pytest.raises(
        FusionCheckpointError, match=r"'layers\.0\.weight' has shape \[32, 40\] in the file but shape"
    ) as e:
        load_fusion(tmp_path / "bad.pth")
    assert e.value.key == "layers.0.weight" and e.value.file_shape == (32, 40)
    assert e.value.model_shape == tuple(ResidualSemanticFusion(CFG).state_dict()["layers.0.weight"].shape)
