"""MASt3R-compatible backbone, RoPE2D and the Splatt3R-style Gaussian head (tiny random-weight networks)."""

from __future__ import annotations

# First, before torch: importing macsplat_cli sets OMP_WAIT_POLICY=PASSIVE, which OpenMP reads when torch
# loads (on 2 busy cores the default spinning made this file ~4x slower).
import math
from pathlib import Path

import pytest
import torch

from macsplat_cli.errors import InputError, ShapeError
from macsplat_cli.gaussians import GaussianMaps
from macsplat_cli.neural import (
    BackboneConfig,
    GaussianHead,
    GaussianHeadConfig,
    MASt3RBackbone,
    RoPE2D,
    conf_activation,
    depth_activation,
    patch_positions,
)
from macsplat_cli.neural.constructor import ModelConfigError
from macsplat_cli.rotations import quat_to_rotmat
from macsplat_cli.sh import C0, rgb_to_sh0

from support.numerics import forward_rel_tol, gamma, max_rel_err, unit_roundoff

TINY = BackboneConfig.tiny()
U32 = unit_roundoff(torch.float32)
U64 = unit_roundoff(torch.float64)


def _forward_tol(model: torch.nn.Module, n_tokens: int) -> float:
    """Relative rounding estimate of one float32 forward pass (``forward_rel_tol``): every Linear/conv/LayerNorm
    of the model, and per attention layer QKᵀ over the head size and the softmax sum and softmax·V over the
    tokens (the encoder's blocks; self- and cross-attention in each decoder block)."""
    enc = TINY.enc_depth * [TINY.enc_embed_dim // TINY.enc_num_heads, n_tokens, n_tokens]
    dec = 2 * TINY.dec_depth * [TINY.dec_embed_dim // TINY.dec_num_heads, n_tokens, n_tokens]
    return forward_rel_tol(model, *enc, *dec)


def _head_gain(raw: torch.Tensor) -> float:
    """How the heads' activations scale a relative error ε of the raw channels (≤ ε·max|raw| absolute): conf =
    1 + eˣ and pts = v/‖v‖·expm1(‖v‖) move by ≤ (1 + max|raw|)·ε·max|raw| relative to their largest value."""
    m = float(raw[..., :4].abs().max())
    return (1 + m) * max(m, 1.0)


def _images(b: int, h: int, w: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, h, w, generator=g) * 2 - 1, torch.rand(b, 3, h, w, generator=g) * 2 - 1


@pytest.fixture(scope="module")
def net() -> MASt3RBackbone:
    torch.manual_seed(0)
    return MASt3RBackbone(TINY).eval()


@pytest.fixture(scope="module")
def gauss_head() -> GaussianHead:
    torch.manual_seed(1)
    return GaussianHead(TINY).eval()


# ============================================================================================= RoPE
def test_patch_positions_are_row_major_y_x() -> None:
    pos = patch_positions(2, 3)
    assert pos.tolist() == [[0, 0], [0, 1], [0, 2], [1, 0], [1, 1], [1, 2]]


def _rope_reference(x: torch.Tensor, pos: torch.Tensor, base: float) -> torch.Tensor:
    """Per-channel loop over the reference's description: y on the first half, x on the second,
    inside each half channel j paired with j + D'/2, angle pos·base^(-2i/D')."""
    out = x.clone()
    dh = x.shape[-1]
    half = dh // 2
    for axis in (0, 1):
        off = axis * half
        for n in range(x.shape[-2]):
            p = float(pos[n, axis])
            for i in range(half // 2):
                theta = p * base ** (-2 * i / half)
                a, b = x[..., n, off + i], x[..., n, off + i + half // 2]
                out[..., n, off + i] = a * math.cos(theta) - b * math.sin(theta)
                out[..., n, off + i + half // 2] = b * math.cos(theta) + a * math.sin(theta)
    return out


def test_rope_matches_the_per_channel_formula() -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 6, 16, generator=g, dtype=torch.float64)
    pos = patch_positions(2, 3)
    got = RoPE2D(100.0)(x, pos)
    # float64: θ = p·base^(−2i/D′) (pow ≤ 2 ulp, ·p: ≤ 4u·|θ| on either side, |θ| ≤ 2), cos/sin to 1 ulp (ATen vs
    # libm), then a·cos − b·sin (3 roundings): per side ≤ (|a| + |b|)·(7u + 8u·|θ|), both ≤ 2·(7 + 16)u·2max|x|
    tol = 2 * (7 + 16) * U64 * 2 * float(x.abs().max())
    torch.testing.assert_close(got, _rope_reference(x, pos, 100.0), rtol=0, atol=tol)


def test_rope_dot_products_depend_only_on_relative_position() -> None:
    g = torch.Generator().manual_seed(1)
    rope = RoPE2D(100.0)
    q = torch.randn(1, 2, 1, 32, generator=g, dtype=torch.float64)
    k = torch.randn(1, 2, 1, 32, generator=g, dtype=torch.float64)
    pq, pk = torch.tensor([[3, 5]]), torch.tensor([[7, 1]])
    base = (rope(q, pq) * rope(k, pk)).sum(-1)
    # float64: each rotated component is off by ≤ (|a| + |b|)·(7u + 8u·|θ|) (|θ| ≤ the largest position, 20), so
    # the 32-term score by ≤ Σ over pairs of (|q|+|q'|)(|k|+|k'|)·2·(7 + 8·20)u, plus γ₃₂ of Σ|qₖkₖ|; two scores
    pair_q = q.abs()[..., :16] + q.abs()[..., 16:]
    pair_k = k.abs()[..., :16] + k.abs()[..., 16:]
    s_abs = float((pair_q * pair_k).sum())
    tol = 2 * (2 * (7 + 8 * 20) * U64 * s_abs + gamma(32, torch.float64) * s_abs)
    for shift in ([0, 4], [9, 0], [11, 13]):
        t = torch.tensor([shift])
        shifted = (rope(q, pq + t) * rope(k, pk + t)).sum(-1)
        torch.testing.assert_close(shifted, base, rtol=0, atol=tol)
    # A change of the relative position does change the score.
    moved = (rope(q, pq) * rope(k, pk + torch.tensor([[0, 1]]))).sum(-1)
    assert (moved - base).abs().max() > 1e-3


def test_rope_preserves_norms_and_splits_axes() -> None:
    g = torch.Generator().manual_seed(2)
    rope = RoPE2D(100.0)
    x = torch.randn(2, 2, 4, 16, generator=g)
    pos = torch.tensor([[0, 0], [1, 5], [3, 2], [7, 7]])
    y = rope(x, pos)
    # float32: cos, sin to 1 ulp make c² + s² = 1 ± 4u (a pair's length ± 2u), the output's 3 roundings ≤ 3√2·u of
    # the pair's length; the two 16-term norms γ₁₆/2 + u each: ≤ 2 + 4.3 + 18 ≤ 25u relative
    torch.testing.assert_close(y.norm(dim=-1), x.norm(dim=-1), rtol=gamma(25, torch.float32), atol=0)
    # position (0, 0) is the identity: sin 0 = 0, cos 0 within an ulp of 1, one rounding of x·cos 0
    torch.testing.assert_close(y[..., 0, :], x[..., 0, :], rtol=2 * U32, atol=0)
    # Changing only x positions leaves the y half (first 8 channels) unchanged, and vice versa: (a) the unchanged
    # half is rotated by its own call, with the same angles and inputs
    y_x = rope(x, pos + torch.tensor([0, 3]))
    assert torch.equal(y_x[..., :8], y[..., :8])
    assert (y_x[..., 8:] - y[..., 8:]).abs().max() > 1e-3
    y_y = rope(x, pos + torch.tensor([2, 0]))
    assert torch.equal(y_y[..., 8:], y[..., 8:])


# ============================================================================================= activations
def test_depth_activation_is_expm1_of_the_norm_along_the_raw_direction() -> None:
    v = torch.tensor([[0.6, 0.8, 0.0], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0]])
    out = depth_activation(v, ("exp", -math.inf, math.inf))
    # float32: d = ‖v‖ (γ₃/2 + u), expm1(d) to 1 ulp and amplifying δd by d·eᵈ/expm1(d) ≤ 1.6, v/d·(…) 2 roundings;
    # the test's float64 constant is rounded to float32 and multiplied (2u): ≤ 12u relative (zeros stay exact)
    torch.testing.assert_close(out[0], v[0] * math.expm1(1.0), rtol=gamma(12, torch.float32), atol=0)
    # d = 2 and v/d = −1 exactly; expm1(2) to 1 ulp (2u) and the constant's rounding (u)
    torch.testing.assert_close(out[1], torch.tensor([0.0, 0.0, -math.expm1(2.0)]), rtol=3 * U32, atol=0)
    assert torch.equal(out[2], torch.zeros(3))  # no NaN at zero
    assert torch.equal(depth_activation(v, ("linear", -math.inf, math.inf)), v)


def test_conf_activation_offsets_and_clips() -> None:
    x = torch.tensor([-30.0, 0.0, 2.0])
    # (a) vmin + exp(x) is the test's own expression: the same exp kernel on the same tensor, and one addition
    assert torch.equal(conf_activation(x, ("exp", 1.0, math.inf)), 1 + x.exp())
    assert torch.equal(conf_activation(x, ("exp", 0.0, math.inf)), x.exp())
    # 1 + e⁻³⁰ rounds to 1, 1 + e⁰ to 2 for an exp within an ulp of 1, and the clip gives 3: ≤ 2u·3 in all
    assert conf_activation(x, ("exp", 1.0, 3.0)).tolist() == pytest.approx([1.0, 2.0, 3.0], rel=0, abs=6 * U32)


# ============================================================================================= backbone
@pytest.mark.parametrize(("h", "w", "b"), [(48, 64, 2), (64, 48, 1), (32, 80, 1), (16, 16, 1)])
def test_output_shapes(net: MASt3RBackbone, h: int, w: int, b: int) -> None:
    img1, img2 = _images(b, h, w)
    with torch.no_grad():
        v1, v2 = net(img1, img2)
    gh, gw = h // 16, w // 16
    for v in (v1, v2):
        assert v.pts3d.shape == (b, h, w, 3)
        assert v.conf.shape == (b, h, w)
        assert v.desc.shape == (b, h, w, 24)
        assert v.desc_conf.shape == (b, h, w)
        assert v.grid == (gh, gw) and v.image_size == (h, w)
        assert len(v.tokens) == TINY.dec_depth + 1
        assert v.enc_tokens.shape == (b, gh * gw, TINY.enc_embed_dim)
        assert v.dec_tokens.shape == (b, gh * gw, TINY.dec_embed_dim)
        assert v.dec_feature_map().shape == (b, TINY.dec_embed_dim, gh, gw)
        assert all(torch.isfinite(t).all() for t in (v.pts3d, v.conf, v.desc, v.desc_conf))


def test_dec_feature_map_is_the_token_grid(net: MASt3RBackbone) -> None:
    with torch.no_grad():
        v1, _ = net(*_images(1, 32, 48))
    fmap = v1.dec_feature_map()
    # token n = y·w + x sits at (y, x): (a) a reshape, no arithmetic
    assert torch.equal(fmap[0, :, 1, 2], v1.dec_tokens[0, 1 * 3 + 2])


@pytest.mark.parametrize(
    ("shape1", "shape2"),
    [
        ((1, 3, 48, 64), (1, 3, 64, 48)),  # different sizes
        ((1, 3, 48, 64), (2, 3, 48, 64)),  # different batch sizes
        ((1, 3, 40, 64), (1, 3, 40, 64)),  # not a multiple of 16
        ((1, 1, 48, 64), (1, 1, 48, 64)),  # not RGB
        ((3, 48, 64), (3, 48, 64)),  # no batch axis
    ],
)
def test_bad_image_shapes_raise_shape_error(net: MASt3RBackbone, shape1: tuple, shape2: tuple) -> None:
    with pytest.raises(ShapeError) as info:
        net(torch.zeros(shape1), torch.zeros(shape2))
    assert isinstance(info.value, InputError)


def test_integer_images_raise_input_error(net: MASt3RBackbone) -> None:
    img = torch.zeros(1, 3, 16, 16, dtype=torch.uint8)
    with pytest.raises(InputError, match="floating-point"):
        net(img, img)


def test_activations_on_the_network_outputs(net: MASt3RBackbone) -> None:
    img1, img2 = _images(1, 48, 64, seed=3)
    with torch.no_grad():
        v1, v2 = net(img1, img2)
        raw = net.downstream_head2.raw(v2.tokens, v2.grid)
    for v in (v1, v2):
        assert v.conf.min() >= 1.0  # conf_mode ('exp', 1, inf)
        assert v.desc_conf.min() > 0.0  # desc_conf_mode ('exp', 0, inf)
        # normalised 24-d descriptors: the normalisation's norm and division (γ₂₄/2 + 2u), the test's norm
        # (γ₂₄/2 + u)
        torch.testing.assert_close(v.desc.norm(dim=-1), torch.ones(v.desc.shape[:-1]), rtol=0,
                                   atol=gamma(24, torch.float32) + 3 * U32)  # fmt: skip
    # The same activations recomputed from the head's raw output (the same kernels on the same tokens, so the same
    # raw): only an exp on another memory layout may round differently, by ≤ 1 ulp (2u) a side
    torch.testing.assert_close(v2.conf, 1 + raw[..., 3].exp(), rtol=gamma(5, torch.float32), atol=0)
    torch.testing.assert_close(v2.desc_conf, raw[..., 28].exp(), rtol=gamma(4, torch.float32), atol=0)
    d = raw[..., :3].norm(dim=-1, keepdim=True)
    # the norm (γ₃/2 + u a side, amplified ≤ 1 + d by expm1), expm1 1 ulp, 2 roundings: ≤ 2·(3(1 + d) + 4)u relative
    rtol = 2 * (3 * (1 + float(d.max())) + 4) * U32
    torch.testing.assert_close(v2.pts3d, raw[..., :3] / d * torch.expm1(d), rtol=rtol, atol=0)


def test_local_features_are_pixel_shuffled_channel_major(net: MASt3RBackbone) -> None:
    """Descriptor channel c of pixel (16y + i, 16x + j) is MLP output c·256 + 16i + j of token (y, x)."""
    with torch.no_grad():
        v1, _ = net(*_images(1, 32, 48, seed=4))
        head = net.downstream_head1
        raw = head.raw(v1.tokens, v1.grid)
        mlp = head.head_local_features(torch.cat((v1.tokens[0], v1.tokens[-1]), dim=-1))  # [1, N, 25·256]
    y, x, i, j, c = 1, 2, 5, 11, 7
    token = y * v1.grid[1] + x
    assert raw[0, 16 * y + i, 16 * x + j, 4 + c] == mlp[0, token, c * 256 + 16 * i + j]


def test_eval_mode_is_deterministic_and_batch_independent(net: MASt3RBackbone) -> None:
    img1, img2 = _images(2, 48, 32, seed=5)
    with torch.no_grad():
        a1, a2 = net(img1, img2)
        b1, b2 = net(img1, img2)
        s1, s2 = net(img1[1:], img2[1:])
        raw2 = net.downstream_head2.raw(a2.tokens, a2.grid)
        raw1 = net.downstream_head1.raw(a1.tokens, a1.grid)
    assert torch.equal(a1.pts3d, b1.pts3d) and torch.equal(a2.desc, b2.desc)  # (a) the same call twice
    # (b) batch 1 vs batch 2 may block the matrix products differently: two float32 orders of the same forward
    # pass, each within _forward_tol (relative to the largest value), scaled by the heads' activations
    # (measured: 5u and 2u)
    tol = 2 * _forward_tol(net, n_tokens=3 * 2)
    assert max_rel_err(s2.pts3d[0], a2.pts3d[1]) <= tol * _head_gain(raw2)
    assert max_rel_err(s1.conf[0], a1.conf[1]) <= tol * _head_gain(raw1)


def test_decoders_cross_attend_symmetrically_when_weights_are_tied() -> None:
    """With dec_blocks2 = dec_blocks and head2 = head1, view 2 of (a, b) equals view 1 of (b, a)."""
    torch.manual_seed(7)
    model = MASt3RBackbone(TINY).eval()
    model.dec_blocks2.load_state_dict(model.dec_blocks.state_dict())
    model.downstream_head2.load_state_dict(model.downstream_head1.state_dict())
    a, b = _images(1, 32, 48, seed=6)
    with torch.no_grad():
        _, ab2 = model(a, b)
        ba1, _ = model(b, a)
        untied = MASt3RBackbone(TINY).eval()
        _, u2 = untied(a, b)
        u1, _ = untied(b, a)
        raw = model.downstream_head1.raw(ba1.tokens, ba1.grid)
    # (b) the same math with the views in the other batch slots: two float32 orders, each within _forward_tol
    # (measured: equal bits). The descriptors are the raw channels 4:28 normalised per pixel: an error of
    # ε·max|raw| moves a unit descriptor by ≤ that over the pixel's raw norm.
    tol = 2 * _forward_tol(model, n_tokens=2 * 3)
    assert max_rel_err(ab2.pts3d, ba1.pts3d) <= tol * _head_gain(raw)
    desc_gain = float(raw[..., 4:28].abs().max() / raw[..., 4:28].norm(dim=-1).min())
    assert max_rel_err(ab2.desc, ba1.desc) <= tol * desc_gain
    assert (u2.pts3d - u1.pts3d).abs().max() > 1e-4  # separate weights do break the symmetry


def test_view_outputs_depend_on_the_other_view(net: MASt3RBackbone) -> None:
    a, b = _images(1, 32, 32, seed=8)
    c, _ = _images(1, 32, 32, seed=9)
    with torch.no_grad():
        v1, _ = net(a, b)
        w1, _ = net(a, c)
    assert (v1.pts3d - w1.pts3d).abs().max() > 1e-5  # cross-attention carries view 2 into view 1
    assert torch.equal(v1.enc_tokens, w1.enc_tokens)  # the encoder sees each image alone


def test_predict_view_uses_given_tokens(net: MASt3RBackbone) -> None:
    """A fusion module can alter the decoder tokens and re-run a head."""
    with torch.no_grad():
        v1, _ = net(*_images(1, 32, 32, seed=10))
        tokens = list(v1.tokens)
        tokens[-1] = tokens[-1] + 0.5
        fused = net.predict_view(1, tokens, v1.grid)
        same = net.predict_view(1, v1.tokens, v1.grid)
    assert torch.equal(same.pts3d, v1.pts3d)
    assert (fused.desc - v1.desc).abs().max() > 1e-4


@pytest.mark.parametrize(("h", "w"), [(384, 512), (512, 336)])
def test_full_size_network_shapes_on_meta(h: int, w: int) -> None:
    """The released ViT-L/ViT-B network and Splatt3R's head, shape-checked without weights (``meta`` device)."""
    cfg = BackboneConfig(head_type="gaussian_head")
    with torch.device("meta"):
        net, head = MASt3RBackbone(cfg), GaussianHead(cfg)
        img = torch.empty(1, 3, h, w)
        v1, v2 = net(img, img)
        g1, g2 = head(v1, v2, img, img)
    assert v2.pts3d.shape == (1, h, w, 3) and v2.desc.shape == (1, h, w, 24) and v2.desc_conf.shape == (1, h, w)
    assert [tuple(t.shape[1:]) for t in v1.tokens] == [(h * w // 256, 1024)] + [(h * w // 256, 768)] * 12
    assert isinstance(g2, GaussianMaps) and g2.valid is None and g2.cam_to_world is None
    assert g2.means.shape == (1, h, w, 3) and g2.sh.shape == (1, h, w, 1, 3) and g2.opacity_logits.shape == (1, h, w)


def test_official_dpt_hooks() -> None:
    assert BackboneConfig().dpt_hooks == (0, 6, 9, 12)
    assert TINY.dpt_hooks == (0, 1, 2, 3)


# ============================================================================================= Gaussian head
def _splatt3r_activation(raw: torch.Tensor, pts3d: torch.Tensor, rgb: torch.Tensor, k: int) -> dict[str, torch.Tensor]:
    """The head's activations as Splatt3R defines them (reference §3.2), in its own layout: the pre-unification
    outputs (means, offsets, scales, (x, y, z, w) rotations, colour-major SH [3, K], opacities [.., 1])."""
    offset, scale, rot, sh, opacity = torch.split(raw, (3, 3, 4, 3 * k, 1), dim=-1)
    d = torch.linalg.vector_norm(offset, dim=-1, keepdim=True)
    offsets = offset / d.clamp_min(1e-8) * (torch.exp(d - 6.0) - math.exp(-6.0))
    sh = sh.reshape(*sh.shape[:-1], 3, k)
    sh = torch.cat((sh[..., :1] + rgb_to_sh0(rgb)[..., None], sh[..., 1:]), dim=-1)
    return dict(
        means=pts3d + offsets,
        offsets=offsets,
        scales=torch.exp(scale),
        rotations=rot / (torch.linalg.vector_norm(rot, dim=-1, keepdim=True) + 1e-8),
        sh=sh,
        opacities=torch.sigmoid(opacity),
    )


@pytest.mark.parametrize("k", [1, 4])
def test_gaussian_head_activations_equal_splatt3rs_exactly(net: MASt3RBackbone, k: int) -> None:
    """Fixed random weights: exp(log_scales), sigmoid(opacity_logits), the quaternions (reordered from xyzw)
    and the SH (transposed) are bit for bit Splatt3R's activated outputs; the means and offsets too."""
    torch.manual_seed(20 + k)
    head = GaussianHead(TINY, GaussianHeadConfig(sh_coeffs=k)).eval()
    img1, img2 = _images(2, 32, 48, seed=21)
    rgb1, rgb2 = (img1 + 1) / 2, (img2 + 1) / 2
    with torch.no_grad():
        v1, v2 = net(img1, img2)
        g1, g2 = head(v1, v2, rgb1, rgb2)
        for view, g, v, rgb in ((1, g1, v1, rgb1), (2, g2, v2, rgb2)):
            holder = head.downstream_head1 if view == 1 else head.downstream_head2
            raw = holder.gaussian_dpt(v.tokens, v.grid)
            want = _splatt3r_activation(raw, v.pts3d, rgb.permute(0, 2, 3, 1), k)
            assert g.means.shape == (2, 32, 48, 3) and g.sh.shape == (2, 32, 48, k, 3)
            assert torch.equal(g.means, want["means"])
            assert torch.equal(torch.exp(g.log_scales), want["scales"])
            assert torch.equal(g.quats, want["rotations"][..., [3, 0, 1, 2]])
            assert torch.equal(torch.sigmoid(g.opacity_logits), want["opacities"][..., 0])
            assert torch.equal(g.sh, want["sh"].transpose(-1, -2))
            maps, offsets = head.activate(raw, v.pts3d, rgb.permute(0, 2, 3, 1))
            assert torch.equal(offsets, want["offsets"]) and torch.equal(maps.means, g.means)


def test_gaussian_head_opacity_logits_are_the_raw_channel() -> None:
    """The opacity logit is the raw channel itself, exact for |raw| up to 30 (logit(sigmoid(raw)) in float32
    loses digits past |raw| ≈ 10 and saturates near 16.6 (sigmoid rounds to 1), clamped to 13.8 before)."""
    head = GaussianHead(TINY, GaussianHeadConfig(sh_coeffs=1))
    opacity = torch.linspace(-30.0, 30.0, 121).reshape(1, 11, 11)
    raw = torch.zeros(1, 11, 11, 14)
    raw[..., -1] = opacity
    maps, _ = head.activate(raw, torch.zeros(1, 11, 11, 3), torch.zeros(1, 11, 11, 3))
    assert torch.equal(maps.opacity_logits, opacity)
    assert torch.equal(maps.log_scales, raw[..., 3:6])
    lossy = torch.logit(torch.sigmoid(opacity), eps=1e-6)  # the former conversion: far off at |raw| = 30
    assert (lossy - opacity).abs().max() > 10


def test_gaussian_head_max_scale_caps_scales_and_their_gradient(tmp_path: Path) -> None:
    """``max_scale``: scales above the cap come out at the cap with no gradient, those below unchanged; the cap
    travels with a macsplat checkpoint (so ``reconstruct`` applies it at test, as the MAC-Splat release does)."""
    head = GaussianHead(TINY, GaussianHeadConfig(sh_coeffs=1, max_scale=0.5))
    raw = torch.zeros(1, 1, 2, 14)
    raw[0, 0, :, 3:6] = torch.tensor([[-3.0, math.log(0.4), 0.0], [math.log(0.5), 2.0, -1.0]])
    raw.requires_grad_(True)
    maps, _ = head.activate(raw, torch.zeros(1, 1, 2, 3), torch.zeros(1, 1, 2, 3))
    cap = math.log(0.5)
    want = torch.where(raw[..., 3:6] > cap, torch.full_like(raw[..., 3:6], cap), raw[..., 3:6])
    assert torch.equal(maps.log_scales, want)
    maps.log_scales.sum().backward()
    assert torch.equal(raw.grad[..., 3:6], (raw[..., 3:6] <= cap).float())  # clamp: gradient 1 up to the cap
    with pytest.raises(ModelConfigError, match="max_scale"):
        GaussianHeadConfig(max_scale=0.0)
    from macsplat_cli.neural.predictor import PairPredictor
    from macsplat_cli.neural.predictor_io import load_predictor_checkpoint, save_predictor_checkpoint

    predictor = PairPredictor(MASt3RBackbone(TINY), head)
    back, _ = load_predictor_checkpoint(save_predictor_checkpoint(tmp_path / "p.pt", predictor))
    assert back.gaussian_head is not None and back.gaussian_head.config.max_scale == 0.5


def test_gaussian_head_outputs(net: MASt3RBackbone, gauss_head: GaussianHead) -> None:
    img1, img2 = _images(2, 48, 64, seed=11)
    rgb1, rgb2 = (img1 + 1) / 2, (img2 + 1) / 2
    with torch.no_grad():
        v1, v2 = net(img1, img2)
        g1, g2 = gauss_head(v1, v2, rgb1, rgb2)
    for view, g, v, rgb in ((1, g1, v1, rgb1), (2, g2, v2, rgb2)):
        holder = gauss_head.downstream_head1 if view == 1 else gauss_head.downstream_head2
        with torch.no_grad():
            raw = holder.gaussian_dpt(v.tokens, v.grid)
            _, offsets = gauss_head.activate(raw, v.pts3d, rgb.permute(0, 2, 3, 1))
        assert isinstance(g, GaussianMaps) and g.batch == 2 and g.size == (48, 64)
        assert g.valid is None and g.cam_to_world is None  # every pixel, view 1's frame
        assert g.means.shape == offsets.shape == g.log_scales.shape == (2, 48, 64, 3)
        assert g.quats.shape == (2, 48, 64, 4) and g.sh.shape == (2, 48, 64, 1, 3)
        assert g.opacity_logits.shape == (2, 48, 64)
        assert torch.equal(g.means, v.pts3d + offsets)  # (a) the head's own addition, on the same numbers
        # rot/(‖rot‖ + 1e-8): the norm and division (γ₄/2 + 2u), the test's norm (γ₄/2 + u), and the 1e-8 itself
        rot_norm = torch.linalg.vector_norm(raw[..., 6:10], dim=-1)
        tol = gamma(4, torch.float32) + 3 * U32 + 1e-8 / rot_norm
        assert ((g.quats.norm(dim=-1) - 1).abs() <= tol).all()
        # Initialisation: offsets "small at init", scales ≈ e^-7, opacity ≈ sigmoid(-2).
        scales, opacities = torch.exp(g.log_scales), torch.sigmoid(g.opacity_logits)
        assert offsets.abs().max() < 1e-3
        assert 1e-4 < scales.min() and scales.max() < 1e-2
        assert opacities.mean().item() == pytest.approx(1 / (1 + math.exp(2)), abs=0.02)
        assert ((opacities > 0) & (opacities < 1)).all()
    # The DC colour is a residual on the pixel colour: within a small residual of RGB2SH(rgb).
    dc_rgb = g1.sh[..., 0, :] * C0 + 0.5
    assert (dc_rgb - rgb1.permute(0, 2, 3, 1)).abs().mean() < 0.5


def test_gaussian_sh_residual_is_exact_with_zero_sh_weights(net: MASt3RBackbone) -> None:
    torch.manual_seed(12)
    head = GaussianHead(TINY, GaussianHeadConfig(sh_coeffs=4)).eval()
    conv = head.downstream_head1.gaussian_dpt.dpt.head[-1]
    with torch.no_grad():
        conv.weight[10:22].zero_()
        conv.bias[10:22].zero_()
        img1, img2 = _images(1, 32, 32, seed=13)
        v1, v2 = net(img1, img2)
        g1, _ = head(v1, v2, (img1 + 1) / 2, (img2 + 1) / 2)
    assert g1.sh.shape == (1, 32, 32, 4, 3)  # band-major
    # (a) zero weights and bias give raw SH of exactly ±0, and 0 + x = x; ((x + 1)/2) permuted equals (x + 1)
    # permuted, halved (halving is exact), so rgb_to_sh0 runs on the same numbers
    assert torch.equal(g1.sh[..., 0, :], rgb_to_sh0((img1 + 1).permute(0, 2, 3, 1) / 2))
    assert torch.equal(g1.sh[..., 1:, :], torch.zeros(1, 32, 32, 3, 3))


def test_gaussian_quaternions_are_splatt3rs_xyzw_reordered() -> None:
    """Splatt3R's rotation channels are (x, y, z, w): raw (0, 0, sin 45°, cos 45°) is +90° about z, which
    the head hands over as the (w, x, y, z) quaternion (cos 45°, 0, 0, sin 45°)."""
    head = GaussianHead(TINY, GaussianHeadConfig(sh_coeffs=1))
    s = math.sqrt(0.5)
    raw = torch.zeros(1, 1, 1, 14)
    raw[..., 6:10] = torch.tensor([0.0, 0.0, s, s])
    maps, _ = head.activate(raw, torch.zeros(1, 1, 1, 3), torch.zeros(1, 1, 1, 3))
    # float32: s rounded once, the norm of (s, s) (γ₂/2 + u), + 1e-8 (< u/2: no change), the division: ≤ 4u
    torch.testing.assert_close(maps.quats[0, 0, 0], torch.tensor([s, 0.0, 0.0, s]), rtol=4 * U32, atol=0)
    r = quat_to_rotmat(maps.quats[0, 0, 0])
    # R(q) in float32 (ROT_MAT = 16u per entry) and the 3-term product (γ₃)
    torch.testing.assert_close(r @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), rtol=0,
                               atol=16 * U32 + gamma(3, torch.float32))  # fmt: skip


def test_gaussian_means_do_not_backpropagate_into_the_point_map(net: MASt3RBackbone, gauss_head: GaussianHead) -> None:
    img1, img2 = _images(1, 16, 16, seed=15)
    with torch.no_grad():
        v1, v2 = net(img1, img2)
    v1.pts3d.requires_grad_(True)
    g1, _ = gauss_head(v1, v2, (img1 + 1) / 2, (img2 + 1) / 2)
    g1.means.sum().backward()
    assert v1.pts3d.grad is None
    assert gauss_head.downstream_head1.gaussian_dpt.dpt.head[-1].weight.grad is not None
    gauss_head.zero_grad(set_to_none=True)


def test_gaussian_head_checks_rgb_shape(net: MASt3RBackbone, gauss_head: GaussianHead) -> None:
    img1, img2 = _images(1, 16, 32)
    with torch.no_grad():
        v1, v2 = net(img1, img2)
        with pytest.raises(ShapeError):
            gauss_head(v1, v2, torch.zeros(1, 3, 32, 16), torch.zeros(1, 3, 16, 32))
