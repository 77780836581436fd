"""The compositing kernels' vectorisable pieces (render/_lanes.py, the block layout of render/_kernels.py)."""

from __future__ import annotations

import numba as nb
import numpy as np
import pytest
import torch

from macsplat_cli.gaussians import Gaussians
from macsplat_cli.render import _kernels, render
from macsplat_cli.render._lanes import S_MAX, exp64, exp_neg, log64
from macsplat_cli.render.composite import bin_tiles
from macsplat_cli.render.projection import project_gaussians

from support.gaussians import pinhole, random_gaussians


@nb.njit(cache=False, error_model="numpy")
def _lane_math(s, out, x, ex, y, lg):  # noqa: ANN001, ANN202
    """``out = exp_neg(s)`` (float32), ``ex = exp64(x)``, ``lg = log64(y)``: one function, compiled once for the
    tests of all three."""
    for i in range(s.shape[0]):
        out[i] = exp_neg(s[i])
    for i in range(x.shape[0]):
        ex[i] = exp64(x[i])
    for i in range(y.shape[0]):
        lg[i] = log64(y[i])


def test_exp_neg_within_one_ulp() -> None:
    """Every 61st float32 in [0, S_MAX] (18 M values, each binade) and the ends: within 1 ulp of exp(−s) (the bound
    the twin comparisons in test_render.py assume; the check of all 1.1e9 values: history/render.md)."""
    top = int(np.array(S_MAX, np.float32).view(np.int32))
    bits = np.concatenate([np.arange(0, top, 61, dtype=np.int32), np.array([1, top - 1, top], np.int32)])
    s = bits.view(np.float32)
    got, none = np.empty_like(s), np.empty(0)
    _lane_math(s, got, none, none, none, none)
    want = np.exp(-s.astype(np.float64))
    ulp = np.spacing(want.astype(np.float32)).astype(np.float64)
    assert got[0] == 1.0 and float((np.abs(got - want) / ulp).max()) <= 1.0


def test_exp64_log64_within_one_ulp_of_the_c_library() -> None:
    """The projection's float64 ``exp`` and ``log`` (render/_project_lanes.py) against numpy's (the C library's,
    ≤ ~0.5 ulp): within 1 ulp on 400 k arguments over their whole range (exp: [−708, 709], every binade of |x| down
    to 1e-300; log: (0, max], subnormals included), so a float32 output, rounded once from float64, is off the
    exact value by at most u₃₂|·| + ~3e-16 relative (test_fused_projection's bounds)."""
    rng = np.random.default_rng(0)
    signs = rng.choice([-1.0, 1.0], 200_000)
    x = np.concatenate([rng.uniform(-708.0, 709.0, 200_000), signs * 10.0 ** rng.uniform(-300, 2.8, 200_000),
                        [0.0, -708.0, 709.0, -0.5 * np.log(2.0), 0.5 * np.log(2.0)]])  # fmt: skip
    tiny_to_max = [5e-324, 2.2250738585072014e-308, 1.0, 2.0, np.finfo(np.float64).max]
    y = np.concatenate([np.exp(rng.uniform(-744.0, 709.0, 400_000)), tiny_to_max])
    ex, lg, none = np.empty_like(x), np.empty_like(y), np.empty(0, np.float32)
    _lane_math(none, none, x, ex, y, lg)
    want_ex, want_lg = np.exp(x), np.log(y)
    assert float((np.abs(ex - want_ex) / np.spacing(want_ex)).max()) <= 1.0
    assert float((np.abs(lg - want_lg) / np.spacing(np.abs(want_lg))).max()) <= 1.0 and lg[-3] == 0.0
    clamped = np.empty(2)
    _lane_math(none, none, np.array([-800.0, 800.0]), clamped, none.astype(np.float64), none.astype(np.float64))
    assert clamped[0] == ex[-4] and clamped[1] == ex[-3], "the argument is clamped to [−708, 709]"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_composite_forward_does_not_depend_on_the_tile_size(dtype: torch.dtype) -> None:
    """A pixel sees the same samples in the same order whatever the tiling, so the forward is bit-identical across
    tile sizes: 8 (one block), 16, 24 (three) and 13 (a partial block), on an image whose edge tiles are partial."""
    w, h = 61, 35
    g = random_gaussians(400, seed=3, dtype=dtype)
    proj = project_gaussians(*g.tensors(), torch.eye(4, dtype=dtype), pinhole(w, h, 0.9 * w, dtype), w, h)
    feats = np.ascontiguousarray(torch.cat([proj.colors, proj.depths[:, None]], -1).numpy())
    arrays = [np.ascontiguousarray(t.detach().numpy()) for t in (proj.means2d, proj.conics, proj.opacities)]
    rect = np.ascontiguousarray(proj.pixel_rect.numpy())
    outs = []
    for tile in (8, 16, 24, 13):
        tiles = bin_tiles(proj.pixel_rect, w, h, tile)
        feat, trans, _, _ = _kernels.composite_forward(*arrays, feats, rect, tiles.offsets, tiles.lists, w, h, tile)
        outs.append((feat, trans))
    assert float(outs[0][1].min()) < 0.5, "the scene must cover the image"
    for feat, trans in outs[1:]:
        assert np.array_equal(feat, outs[0][0]) and np.array_equal(trans, outs[0][1])


def test_composite_forward_refuses_other_feature_counts() -> None:
    z = np.zeros((1, 3), np.float32)
    with pytest.raises(ValueError, match="4 features"):
        _kernels.composite_forward(z[:, :2], z, z[:, 0], z, np.zeros((1, 4), np.int32), np.zeros(2, np.int64),
                                   np.zeros(0, np.int32), 4, 4, 16)  # fmt: skip


def _render_and_grads(g: Gaussians, w: int, h: int):  # noqa: ANN202
    params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
    out = render(Gaussians(*params), torch.eye(4), pinhole(w, h), w, h, backend="numba")
    loss = (out.rgb * torch.linspace(-1, 1, 3)).sum() + out.depth.mean() + out.alpha.sum()
    return out, torch.autograd.grad(loss, params)


@pytest.mark.parametrize(("cap", "full_again"), [(900, False), (4, True)])
def test_lazy_binning_renders_as_the_full_lists(monkeypatch: pytest.MonkeyPatch, cap: int, full_again: bool) -> None:
    """Lists capped at ``cap`` entries (1,500 opaque Gaussians, 470–1,200 a tile; every tile's pixels are done
    within its first 730): the image and every gradient bit-identical to the full lists'; a cap that leaves pixels
    not done (4) bins and composites again in full."""
    g = random_gaussians(1500, seed=7, scale_range=(0.08, 0.3), opacity_logit_range=(3.0, 8.0))
    want, want_grads = _render_and_grads(g, 40, 32)
    assert float(want.alpha.detach().min()) > 0.99, "every pixel must be done"
    monkeypatch.setattr(_kernels, "LAZY_CAP", cap)
    monkeypatch.setattr(_kernels, "LAZY_MEAN", 8)
    full_bins = []
    monkeypatch.setattr(_kernels, "bin_tiles", lambda *a: full_bins.append(1) or _kernels._bin(*a, False)[:2])
    got, grads = _render_and_grads(g, 40, 32)
    assert bool(full_bins) == full_again
    assert got.n_intersections == want.n_intersections
    for a, b in zip((got.rgb, got.depth, got.alpha, *grads), (want.rgb, want.depth, want.alpha, *want_grads)):
        assert torch.equal(a, b)
