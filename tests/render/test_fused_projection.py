"""The fused projection kernel (render/fused.py) against its plain-PyTorch twin (render/projection.py): the kept set,
its order, every output and every parameter's gradient; float64 gradcheck; the depth sort; the camera-gradient path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from macsplat_cli.gaussians import Gaussians
from macsplat_cli.render import render
from macsplat_cli.render._project_kernels import depth_order
from macsplat_cli.render.fused import project_gaussians_fused
from macsplat_cli.render.projection import project_gaussians

from support.gaussians import pinhole, random_gaussians
from support.numerics import GC_ATOL, GC_EPS, GC_RTOL, assert_within, gamma, unit_roundoff

FIELDS = ("means2d", "conics", "depths", "opacities", "colors")
PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")
FWD_OPS = 64
"""Rounded operations on the longest path from a parameter to an output (mean → J → M2 → det → conic: ~50)."""
BWD_OPS = 256
"""The same for a gradient: the forward's chain recomputed, then walked back through every use of each value."""


def _camera(dtype: torch.dtype, w: int, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A rotated, translated camera with a skewed K, so that every term of the projection is exercised."""
    V = torch.eye(4, dtype=torch.float64)
    w_hat = torch.tensor([[0.0, -0.1, 0.05], [0.1, 0.0, -0.02], [-0.05, 0.02, 0.0]], dtype=torch.float64)
    V[:3, :3] = torch.linalg.matrix_exp(w_hat)
    V[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    K = pinhole(w, h, 0.9 * w, torch.float64)
    K[0, 1] = 1.5
    return V.to(dtype), K.to(dtype)


def _with_hard_cases(g: Gaussians) -> Gaussians:
    """``g`` plus Gaussians on every guard: culled (NaN, behind the camera, faint, off-screen), capped scales, a zero
    quaternion, far to the side (the Jacobian's clamp), and one on the image edge."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [0.1, 0.0, 2.0], [50.0, 0.0, 2.0], [0.0, 0.1, 3.0],
                          [-0.2, 0.1, 2.5], [1.8, -0.3, 2.0], [0.0, 1.3, 2.2]])  # fmt: skip
    log_scales = torch.full((8, 3), -3.0)
    log_scales[4] = torch.tensor([-3.0, 40.0, -2.0])  # past the screen-size cap on one axis
    quats = torch.tensor([[1.0, 0.2, 0.0, 0.1]]).repeat(8, 1)
    quats[5] = 0.0
    logits = torch.tensor([0.5, 0.5, -9.0, 0.5, 0.5, 0.5, 0.5, 0.5])
    means[0, 0] = float("nan")
    sh = torch.randn(8, g.sh.shape[1], 3, generator=torch.Generator().manual_seed(3)) * 0.5
    extra = Gaussians(means, log_scales, quats, logits, sh).to(g.dtype)
    return Gaussians(*(torch.cat([a, b]) for a, b in zip(g.tensors(), extra.tensors())))


def _projection_and_vjp(fn, g: Gaussians, V: torch.Tensor, K: torch.Tensor, w: int, h: int, cots: list | None):  # noqa: ANN001
    """``fn``'s projection and the parameters' gradients of Σ output·cotangent (random cotangents when None)."""
    params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
    p = fn(*params, V, K, w, h)
    outs = [getattr(p, f) for f in FIELDS]
    if cots is None:
        gen = torch.Generator().manual_seed(11)
        cots = [torch.randn(o.shape, generator=gen, dtype=torch.float64) for o in outs]
    cots = [c.to(outs[0].dtype).double() for c in cots]  # representable in the outputs' dtype
    loss = sum((o * c.to(o.dtype)).sum() for o, c in zip(outs, cots))
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return p, grads, cots


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_fused_projection_matches_twin(dtype: torch.dtype, sh_degree: int) -> None:
    """Against the twin evaluated in float64 on the same (float32-rounded) inputs. The kernel computes in float64
    and rounds each output once, so a float32 result is within half an ulp (u₃₂|ref|) of the exact value (the depth,
    summed in the inputs' dtype as the twin sums it: γ₄ of its terms); the two
    float64 evaluations order their ≤ n operations differently: 2γₙ (n = FWD_OPS, BWD_OPS) relative to each output's
    largest value, first order (the values are O(1)-conditioned: det ≥ ε², z > near)."""
    w, h = 48, 40
    g = _with_hard_cases(random_gaussians(200, seed=sh_degree, dtype=dtype, sh_degree=sh_degree))
    V, K = _camera(dtype, w, h)
    fast, v_fast, cots = _projection_and_vjp(project_gaussians_fused, g, V, K, w, h, None)
    ref, v_ref, _ = _projection_and_vjp(project_gaussians, g.to(torch.float64), V.double(), K.double(), w, h, cots)
    assert len(ref) > 150 and not set(ref.ids.tolist()) & {200, 201, 202, 203}, "the culls must have culled"
    assert torch.equal(fast.ids, ref.ids), "the same Gaussians kept, in the same order"
    assert torch.equal(fast.pixel_rect, ref.pixel_rect)
    u = unit_roundoff(dtype) if dtype == torch.float32 else 0.0
    for name in FIELDS:
        a, b = getattr(fast, name).double(), getattr(ref, name).detach()
        bound = u * b.abs() + 2 * gamma(FWD_OPS, torch.float64) * b.abs().max()
        if name == "depths":  # R₂·m + t₂ summed in the inputs' dtype, as the twin does (the order of ties)
            terms = g.means.double()[ref.ids].abs() @ V[2, :3].double().abs() + V[2, 3].double().abs()
            bound = bound + gamma(4, dtype) * terms
        assert_within(a, b, bound, name)
    for name, a, b in zip(PARAMS, v_fast, v_ref):
        assert b.abs().max() > 0, f"{name}: the reference gradient is all zero"
        assert_within(a.double(), b, u * b.abs() + 2 * gamma(BWD_OPS, torch.float64) * b.abs().max(), f"d {name}")
    assert float(v_fast[1][204].abs().max()) > 0 and float(v_fast[1][204, 1]) == 0.0, "no gradient past the cap"
    assert float(v_fast[2][205].abs().max()) == 0.0, "a zero quaternion: the identity, no gradient"


def _tiny(sh_degree: int) -> Gaussians:
    """Five Gaussians in a 16×12 image, none near a cull or clamp threshold."""
    g = torch.Generator().manual_seed(5)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.3, -0.2, 2.5], [-0.25, 0.2, 3.0], [0.1, 0.25, 2.2], [-0.1, -0.3, 2.7]])
    log_scales = torch.log(torch.rand(5, 3, generator=g) * 0.2 + 0.05)
    quats = torch.randn(5, 4, generator=g)
    logits = torch.tensor([0.5, 1.0, -0.5, 0.0, 2.0])
    sh = torch.randn(5, (sh_degree + 1) ** 2, 3, generator=g) * 0.3
    sh[:, 0] += 1.0  # colours away from the clamp at 0
    return Gaussians(means, log_scales, quats, logits, sh).to(torch.float64)


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_gradcheck_fused_projection_float64(sh_degree: int) -> None:
    w, h = 16, 12
    V, K = _camera(torch.float64, w, h)
    params = [t.clone().requires_grad_(True) for t in _tiny(sh_degree).tensors()]

    def fn(*p):  # noqa: ANN002, ANN202
        proj = project_gaussians_fused(*p, V, K, w, h)
        assert len(proj) == 5
        return tuple(getattr(proj, f) for f in FIELDS)

    assert torch.autograd.gradcheck(fn, params, eps=GC_EPS, atol=GC_ATOL, rtol=GC_RTOL)


def _depth_order(keep: np.ndarray, bits: np.ndarray) -> np.ndarray:
    """``depth_order`` on scratch buffers longer than needed and full of another sort's values."""
    n = keep.shape[0] + 5
    idx, idx2 = np.arange(n, 0, -1, dtype=np.int64), np.full(n, 7, np.int64)
    keys, keys2 = np.full(n, 2**63 + 5, np.uint64), np.arange(n, dtype=np.uint64)
    m = depth_order(keep, bits, idx, keys, idx2, keys2)
    return idx[:m]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_order_is_a_stable_argsort(dtype: type) -> None:
    """The radix sort against numpy's stable argsort: ties (in index order), negative and signed-zero-free values,
    culled entries, one repeated value, nothing kept; its scratch holding stale values."""
    rng = np.random.default_rng(0)
    z = rng.choice(np.array([-2.5, -1e-3, 1e-30, 0.5, 2.0, 2.0000002, 3.75, 1e20], dtype), size=3000)
    z[::7] = rng.uniform(-5, 5, size=z[::7].shape).astype(dtype)
    keep = rng.random(3000) < 0.8
    bits = z.view(np.uint32 if dtype == np.float32 else np.uint64)
    sel = np.flatnonzero(keep)
    assert np.array_equal(_depth_order(keep, bits), sel[np.argsort(z[sel], kind="stable")])
    same = np.full(50, 2.0, dtype)
    assert np.array_equal(_depth_order(np.ones(50, np.bool_), same.view(bits.dtype)), np.arange(50))
    assert _depth_order(np.zeros(50, np.bool_), same.view(bits.dtype)).shape == (0,)
    low = np.arange(300, dtype=dtype)[::-1].copy()  # keys differ in their low byte only: one pass, the result swapped
    assert np.array_equal(_depth_order(np.ones(300, np.bool_), low.view(bits.dtype)), np.arange(300)[::-1])


def test_camera_gradient_goes_through_the_twin() -> None:
    """A viewmat that requires a gradient gets one (the twin's projection; the fused kernel has no camera
    gradient), and the Gaussians' gradients are those of the fused path within float32 rounding."""
    w, h = 32, 24
    g = random_gaussians(100, seed=4)
    K = pinhole(w, h, 0.9 * w)
    grads = []
    for with_camera in (False, True):
        V = torch.eye(4).requires_grad_(with_camera)
        params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
        out = render(Gaussians(*params), V, K, w, h)
        out.rgb.sum().backward()
        grads.append(params[0].grad)
        if with_camera:
            assert V.grad is not None and float(V.grad[:3].abs().max()) > 0
    assert torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-4 * float(grads[1].abs().max()))


def test_coincident_gaussians_keep_the_twins_order() -> None:
    """Gaussians one rounding apart (three views' maps of one surface) tie in depth or not as the twin's float32 depth
    says, so that their compositing order, and the image where they overlap, is the twin's: the kernel sums the
    depth in the inputs' dtype in the twin's order (a float64 depth rounded once broke some of them)."""
    w, h = 64, 48
    g = random_gaussians(400, seed=9, dtype=torch.float32)
    gen = torch.Generator().manual_seed(9)
    copies = [g.means + g.means * torch.randint(-2, 3, g.means.shape, generator=gen) * 2.0**-23 for _ in range(3)]
    g3 = Gaussians(torch.cat(copies), *(torch.cat([t] * 3) for t in g.tensors()[1:]))
    V, K = _camera(torch.float32, w, h)
    with torch.no_grad():
        ref = project_gaussians(*g3.tensors(), V, K, w, h)
        fast = project_gaussians_fused(*g3.tensors(), V, K, w, h)
    assert int((ref.depths[1:] == ref.depths[:-1]).sum()) > 100, "the scene must have ties"
    assert torch.equal(fast.depths, ref.depths) and torch.equal(fast.ids, ref.ids)
