"""The CPU rasterizer: Numba kernels against the plain-PyTorch twin, gradients, numerics."""

from __future__ import annotations

import math

import pytest
import torch

from macsplat_cli.gaussians import Gaussians
from macsplat_cli.render import render
from macsplat_cli.render.composite import bin_tiles, composite
from macsplat_cli.render.projection import project_gaussians
from macsplat_cli.render.reference import composite_reference

from support.gaussians import pinhole, random_gaussians
from support.numerics import GC_ATOL, GC_EPS, GC_RTOL, assert_within, gamma, max_rel_err, unit_roundoff

EYE = torch.eye(4)
BACKGROUND = (0.1, 0.2, 0.3)


def _twin_bounds(g: Gaussians, K: torch.Tensor, w: int, h: int) -> tuple[float, float, float]:
    """First-order bounds on |Numba − twin| for (rgb, depth·alpha, alpha), absolute. The kernel and the twin evaluate
    the same float32 σ = ½(a·dx² + c·dy²) + b·dx·dy and the same skip rules; exp differs by ≤ 1 ulp a side, so α by
    ≤ ε = 4u relative. C = Σ cᵢαᵢTᵢ has |∂C/∂αⱼ| ≤ 2·max|c|·Tⱼ (the later samples' share T_{j+1}/(1 − αⱼ) = Tⱼ), so
    Σⱼ Tⱼαⱼε ≤ ε: |ΔC| ≤ 2ε·max|c|, |ΔT| ≤ ε. The ≤ n samples of a pixel are accumulated (C, T) in two orders: 2γ₂ₙ of
    max|c|. depth·alpha = Σwz is C with c = z (depth divides by 1 − T, which a faint pixel's rounding makes ill
    conditioned: compared as depth·alpha, which adds the division's and the product's roundings, 2u a side)."""
    u = unit_roundoff(g.dtype)
    proj = project_gaussians(*g.tensors(), EYE.to(g.dtype), K.to(g.dtype), w, h)
    acc = 2 * 4 * u + 2 * gamma(2 * len(g), g.dtype)
    c_max = float(proj.colors.max()) if len(proj.colors) else 0.0
    z_max = float(proj.depths.max()) if len(proj.depths) else 0.0
    bg = max(BACKGROUND)
    return acc * c_max + (4 * u + gamma(2 * len(g), g.dtype)) * bg, (acc + 4 * u) * z_max, acc


def _outputs_and_vjp(g: Gaussians, backend: str, K: torch.Tensor, w: int, h: int, seed: int):
    params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
    out = render(Gaussians(*params), EYE.to(g.dtype), K.to(g.dtype), w, h, background=BACKGROUND, backend=backend)
    gen = torch.Generator().manual_seed(seed + 1000)
    cot = [torch.randn(t.shape, generator=gen, dtype=t.dtype) for t in (out.rgb, out.depth, out.alpha)]
    loss = sum((o * v).sum() for o, v in zip((out.rgb, out.depth, out.alpha), cot))
    grads = torch.autograd.grad(loss, params)
    return out, grads


def _assert_twins_agree(g, K, w, h, fast, ref, v_fast, v_ref, grad_factor: float) -> None:  # noqa: ANN001
    """Outputs within :func:`_twin_bounds`. Gradients, relative to their largest value: the VJP recovers T by
    dividing by 1 − α going backwards (gain ≤ 1/(1 − α) per step), for which no useful a-priori bound exists; we
    allow ``grad_factor`` times the forward's relative bound (measured: ≤ 150u, against ≥ 10 × 168u allowed)."""
    b_rgb, b_wz, b_alpha = _twin_bounds(g, K, w, h)
    assert_within(fast.rgb, ref.rgb, b_rgb, "rgb")
    assert_within(fast.depth * fast.alpha, ref.depth * ref.alpha, b_wz, "Σwz")
    assert_within(fast.alpha, ref.alpha, b_alpha, "alpha")
    rel = b_alpha  # ε and the accumulation, relative
    for name, a, b in zip(("means", "log_scales", "quats", "opacity_logits", "sh"), v_fast, v_ref):
        assert b.abs().max() > 0, f"{name}: reference gradient is all zero"
        assert max_rel_err(a, b) <= grad_factor * rel, name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("w", "h", "n", "sh_degree"), [(32, 24, 40, 0), (37, 23, 150, 3), (64, 48, 300, 1)])
def test_numba_matches_torch_twin(dtype: torch.dtype, seed: int, w: int, h: int, n: int, sh_degree: int) -> None:
    g = random_gaussians(n, seed=seed, dtype=dtype, sh_degree=sh_degree)
    K = pinhole(w, h, focal=0.9 * w)
    fast, v_fast = _outputs_and_vjp(g, "numba", K, w, h, seed)
    ref, v_ref = _outputs_and_vjp(g, "torch", K, w, h, seed)
    assert ref.alpha.detach().max() > 0.5, "the scene must cover the image for the comparison to mean anything"
    _assert_twins_agree(g, K, w, h, fast, ref, v_fast, v_ref, grad_factor=10)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_matches_twin_when_pixels_saturate(dtype: torch.dtype) -> None:
    """Opaque, overlapping Gaussians: early termination (T ≤ 1e-4) and the 0.99 clamp are hit."""
    g = random_gaussians(300, seed=7, dtype=dtype, scale_range=(0.08, 0.3), opacity_logit_range=(3.0, 8.0))
    K = pinhole(40, 32)
    fast, v_fast = _outputs_and_vjp(g, "numba", K, 40, 32, 7)
    ref, v_ref = _outputs_and_vjp(g, "torch", K, 40, 32, 7)
    assert float((1 - ref.alpha.detach()).min()) < 1e-3, "some pixels must saturate"
    _assert_twins_agree(g, K, 40, 32, fast, ref, v_fast, v_ref, grad_factor=20)


def _tiny_projection(dtype: torch.dtype = torch.float64):
    """Four Gaussians in a 12×10 image, chosen so that no pixel sits near a skip threshold."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.3, -0.2, 2.5], [-0.25, 0.2, 3.0], [0.1, 0.25, 2.2]], dtype=dtype)
    log_scales = torch.log(
        torch.tensor([[0.15, 0.1, 0.1], [0.2, 0.12, 0.1], [0.25, 0.2, 0.1], [0.1, 0.15, 0.2]], dtype=dtype)
    )
    quats = torch.tensor(
        [[1.0, 0.1, 0.0, 0.2], [0.9, 0.0, 0.3, 0.0], [1.0, 0.0, 0.0, 0.0], [0.7, 0.2, 0.1, 0.4]], dtype=dtype
    )
    logits = torch.tensor([0.5, 1.0, -0.5, 0.0], dtype=dtype)
    sh = torch.tensor([[[1.0, 0.2, -0.5]], [[-0.3, 0.8, 0.1]], [[0.4, -0.6, 0.9]], [[0.0, 0.5, -0.2]]], dtype=dtype)
    return Gaussians(means, log_scales, quats, logits, sh)


def test_gradcheck_numba_composite_float64() -> None:
    g = _tiny_projection()
    w, h = 12, 10
    proj = project_gaussians(*g.tensors(), torch.eye(4, dtype=torch.float64), pinhole(w, h, 10.0, torch.float64), w, h)
    feats = torch.cat([proj.colors, proj.depths[:, None]], -1)
    tiles = bin_tiles(proj.pixel_rect, w, h, tile=8)  # several tiles, one partial
    inputs = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, proj.opacities, feats)]

    def fn(m2, con, op, f):  # noqa: ANN001, ANN202
        return composite(m2, con, op, f, proj.pixel_rect, w, h, tiles=tiles)

    assert torch.autograd.gradcheck(fn, inputs, eps=GC_EPS, atol=GC_ATOL, rtol=GC_RTOL)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_gradcheck_full_render_float64(backend: str) -> None:
    g = _tiny_projection()
    w, h = 12, 10
    K = pinhole(w, h, 10.0, torch.float64)
    V = torch.eye(4, dtype=torch.float64)
    V[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    params = [t.clone().requires_grad_(True) for t in g.tensors()]

    def fn(*p):  # noqa: ANN002, ANN202
        out = render(Gaussians(*p), V, K, w, h, background=(0.3, 0.5, 0.7), backend=backend)
        return out.rgb, out.depth, out.alpha

    assert torch.autograd.gradcheck(fn, params, eps=GC_EPS, atol=GC_ATOL, rtol=GC_RTOL)


def test_single_gaussian_matches_hand_computation() -> None:
    """An isotropic Gaussian on the optical axis: alpha at each pixel is o·exp(−½ d²/σ²)."""
    s, z, f, w, h = 0.1, 2.0, 20.0, 16, 16
    op = 0.8
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, z]]),
        log_scales=torch.full((1, 3), math.log(s)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        opacity_logits=torch.tensor([math.log(op / (1 - op))]),
        sh=torch.zeros(1, 1, 3),
    )
    out = render(g, torch.eye(4), pinhole(w, h, f), w, h)
    var = (f * s / z) ** 2 + 0.3  # projected variance + the 0.3 px² dilation
    u = unit_roundoff(torch.float32)
    for i, j in [(8, 8), (7, 8), (8, 11), (4, 12)]:
        d2 = (j + 0.5 - 8.0) ** 2 + (i + 0.5 - 8.0) ** 2
        sigma = 0.5 * d2 / var
        alpha = op * math.exp(-sigma)
        expected = alpha if alpha >= 1 / 255 else 0.0
        # (c) float32 against float64: the variance from fl(ln s) (2.3u in s, doubled), exp (2u, doubled) and JΣJᵀ
        # plus the dilation (≤ 6u) is ≤ 16u off, σ by ≤ 19u relative with its own roundings, so α by ≤ 19σu, plus
        # exp's ulp (2u), the opacity (sigmoid of a rounded logit, ≤ 3u) and the product (u)
        rel_a = (6 + 19 * sigma) * u
        # alpha = 1 − T with T = fl(1 − α): the cancellation adds u·(1 − α)/α
        assert float(out.alpha[i, j]) == pytest.approx(expected, rel=rel_a + u * (1 - alpha) / alpha, abs=0)
        if expected:
            # colour 0.5 (exact from zero SH), black bg: w·c adds one rounding
            assert float(out.rgb[i, j, 0]) == pytest.approx(0.5 * alpha, rel=rel_a + u, abs=0)
            # depth = Σwz / (1 − T): z = 2 exactly; the cancellation in 1 − T costs u·(1 − α)/α, two roundings
            assert float(out.depth[i, j]) == pytest.approx(z, rel=(2 + (1 - alpha) / alpha) * u, abs=0)


def test_empty_scene_renders_background() -> None:
    out = render(Gaussians.empty(), torch.eye(4), pinhole(20, 10), 20, 10, background=(0.25, 0.5, 1.0))
    assert torch.equal(out.rgb, torch.tensor([0.25, 0.5, 1.0]).expand(10, 20, 3))
    assert torch.equal(out.alpha, torch.zeros(10, 20))
    assert torch.equal(out.depth, torch.zeros(10, 20))


def test_depth_of_an_opaque_wall() -> None:
    """A dense grid of opaque flat Gaussians at z = 3 renders depth 3 and alpha ≈ 1."""
    ys, xs = torch.meshgrid(torch.linspace(-1.7, 1.7, 56), torch.linspace(-1.7, 1.7, 56), indexing="ij")
    n = xs.numel()
    means = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.full((n,), 3.0)], -1)
    g = Gaussians(
        means,
        torch.log(torch.tensor([0.06, 0.06, 0.001])).expand(n, 3).clone(),
        torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(),
        torch.full((n,), 5.0),
        torch.zeros(n, 1, 3),
    )
    out = render(g, torch.eye(4), pinhole(32, 32, 32.0), 32, 32)
    assert float(out.alpha.min()) > 0.99
    # Σwz and 1 − T = Σw (in exact arithmetic) are accumulated over ≤ K samples a pixel (γ₂ₖ each; K ≤ 34: the
    # footprints (3σ = 0.18) of centres 0.062 apart), z = 3 exactly; the division and T ≤ 0.01 add ≤ 3u
    rtol = 2 * gamma(2 * 34, torch.float32) + 3 * unit_roundoff(torch.float32)
    assert torch.allclose(out.depth, torch.full((32, 32), 3.0), rtol=rtol, atol=0)


def test_sh_degree_one_depends_on_view_direction() -> None:
    """Band-1 coefficient 'x' (index 3) brightens Gaussians seen from −x and darkens them from +x."""
    sh = torch.zeros(1, 4, 3)
    sh[0, 3] = 1.0
    g = Gaussians(
        torch.tensor([[0.0, 0.0, 0.0]]),
        torch.full((1, 3), math.log(0.3)),
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.tensor([4.0]),
        sh,
    )
    colours = []
    for cam_x in (-1.0, 1.0):  # camera at (cam_x, 0, -3) looking at the origin, no rotation needed for x ≈ 0
        V = torch.eye(4)
        V[:3, 3] = torch.tensor([-cam_x, 0.0, 3.0])
        out = render(g, V, pinhole(16, 16, 16.0), 16, 16)
        colours.append(float(out.rgb[..., 0].max()))
    # dir = (mean − camera) has x = −cam_x; colour = 0.5 − C1·x·1, so camera at −x sees more red.
    assert colours[0] < colours[1]


# ---------------------------------------------------------------------------- numerical robustness


def _assert_finite_render_and_grads(g: Gaussians, V: torch.Tensor | None = None) -> tuple:
    params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
    out = render(Gaussians(*params), EYE if V is None else V, pinhole(32, 24), 32, 24, background=(1.0, 1.0, 1.0))
    for name in ("rgb", "depth", "alpha"):
        assert torch.isfinite(getattr(out, name)).all(), name
    loss = out.rgb.sum() + out.depth.sum() + out.alpha.sum()
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    for name, gr in zip(("means", "log_scales", "quats", "opacity_logits", "sh"), grads):
        assert gr is None or torch.isfinite(gr).all(), name
    return out, grads


def test_gaussians_behind_and_on_the_camera_plane() -> None:
    g = random_gaussians(60, seed=3, z_range=(-2.0, 2.0))
    g.means[:5, 2] = 0.0  # exactly on the camera plane
    g.means[5:10, 2] = 1e-9
    g.means[10:12] = 0.0  # at the camera centre
    out, grads = _assert_finite_render_and_grads(g)
    assert set(out.visible.tolist()).isdisjoint(range(12))
    assert torch.all(grads[0][:12] == 0)


def test_zero_and_tiny_quaternions() -> None:
    g = random_gaussians(40, seed=4)
    g.quats[:10] = 0.0
    g.quats[10:20] *= 1e-30
    _assert_finite_render_and_grads(g)


@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1.0, 1e2, 1e4])
def test_extreme_scales(scale: float) -> None:
    g = random_gaussians(40, seed=5, z_range=(0.011, 4.0))
    g.log_scales[:] = math.log(scale)
    out, _ = _assert_finite_render_and_grads(g)
    if scale >= 1.0:
        assert float(out.alpha.detach().min()) > 0.5  # huge Gaussians cover the whole image


def test_huge_log_scales_and_near_plane() -> None:
    g = random_gaussians(20, seed=6, z_range=(0.0101, 0.02))
    g.log_scales[:10] = 80.0  # exp overflows float32 without the screen-size cap
    _assert_finite_render_and_grads(g)


def test_nan_and_inf_parameters_are_culled() -> None:
    g = random_gaussians(50, seed=8)
    g.means[0, 0] = float("nan")
    g.log_scales[1, 2] = float("inf")
    g.quats[2, 1] = float("-inf")
    g.opacity_logits[3] = float("nan")
    g.sh[4, 0, 1] = float("inf")
    g.opacity_logits[5] = float("inf")  # opacity 1 written as an infinite logit is also rejected
    out, grads = _assert_finite_render_and_grads(g)
    assert set(out.visible.tolist()).isdisjoint(range(6))
    for gr in grads:
        assert torch.all(gr[:6] == 0)
    clean = render(g[torch.arange(6, 50)], EYE, pinhole(32, 24), 32, 24, background=(1.0, 1.0, 1.0))
    assert torch.equal(out.rgb, clean.rgb)


def test_far_off_screen_gaussian_has_bounded_footprint() -> None:
    """The clamped Jacobian keeps a Gaussian far outside the view from smearing across it."""
    g = Gaussians(
        torch.tensor([[50.0, 0.0, 1.0]]),
        torch.full((1, 3), math.log(0.5)),
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.tensor([5.0]),
        torch.zeros(1, 1, 3),
    )
    out = render(g, EYE, pinhole(32, 32), 32, 32)
    assert float(out.alpha.max()) < 1 / 255


def test_twin_handles_no_visible_gaussians() -> None:
    feat, trans = composite_reference(torch.zeros(0, 2), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 4), 5, 4)
    assert feat.shape == (4, 5, 4) and torch.equal(trans, torch.ones(4, 5))
