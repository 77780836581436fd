"""The Multi-Attribute Consistency loss."""

from __future__ import annotations

import math

import pytest
import torch

from macsplat_cli.errors import InputError, NonFiniteError
from macsplat_cli.gaussians import GaussianMaps
from macsplat_cli.mac import MACConfig, huber, mac_loss, sample_maps
from macsplat_cli.rotations import quat_to_rotmat

from support.numerics import GC_ATOL, GC_EPS, GC_RTOL, gamma, unit_roundoff

D = torch.float64
U64 = unit_roundoff(D)


def _maps(b: int, h: int, w: int, seed: int, k: int = 4, dtype: torch.dtype = D) -> GaussianMaps:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(b, h, w, 3, generator=g, dtype=dtype) * 0.3
    means[..., 2] = means[..., 2].abs() + 2.0
    opacity_logits = torch.logit(torch.rand(b, h, w, generator=g, dtype=dtype))
    sh = torch.randn(b, h, w, k, 3, generator=g, dtype=dtype)
    return GaussianMaps(
        means=means,
        log_scales=torch.randn(b, h, w, 3, generator=g, dtype=dtype) * 0.5 - 3.0,
        quats=torch.randn(b, h, w, 4, generator=g, dtype=dtype),
        opacity_logits=opacity_logits,
        sh=sh,
    )


def _cov(m: GaussianMaps) -> torch.Tensor:
    """The maps' Gaussians as raw camera-frame covariances R S² Rᵀ. [B, H, W, 3, 3]"""
    R = quat_to_rotmat(m.quats)
    S2 = torch.diag_embed(torch.exp(2 * m.log_scales))
    return R @ S2 @ R.transpose(-1, -2)


def _one_pixel(log_scales: torch.Tensor | None = None, **fields: torch.Tensor) -> GaussianMaps:
    """A 1×1 map with an identity rotation (and unit scales unless given)."""
    dtype = fields["means"].dtype
    ls = log_scales if log_scales is not None else torch.zeros(1, 1, 1, 3, dtype=dtype)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype).reshape(1, 1, 1, 4)
    return GaussianMaps(log_scales=ls.reshape(1, 1, 1, 3), quats=quats, **fields)


def _poses(b: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(2):
        T = torch.eye(4, dtype=D).repeat(b, 1, 1)
        T[:, :3, :3] = quat_to_rotmat(torch.randn(b, 4, generator=g, dtype=D))
        T[:, :3, 3] = torch.randn(b, 3, generator=g, dtype=D)
        out.append(T)
    return out[0], out[1]


def _matches(b: int, h: int, w: int, m: int, seed: int):  # noqa: ANN202
    g = torch.Generator().manual_seed(seed)
    xy1 = torch.rand(m, 2, generator=g, dtype=D) * torch.tensor([w, h], dtype=D)
    xy2 = torch.rand(m, 2, generator=g, dtype=D) * torch.tensor([w, h], dtype=D)
    batch = torch.randint(0, b, (m,), generator=g)
    wts = torch.rand(m, generator=g, dtype=D)
    return xy1, xy2, batch, wts


def test_sample_maps_matches_hand_bilinear_interpolation() -> None:
    maps = torch.arange(2 * 3 * 4 * 2, dtype=D).reshape(2, 3, 4, 2)
    xy = torch.tensor([[0.5, 0.5], [1.0, 0.5], [1.25, 1.75], [3.5, 2.5], [-3.0, 9.0]], dtype=D)
    out = sample_maps(maps, xy, torch.tensor([0, 0, 1, 1, 0]))
    # float64: grid_sample normalises the position (2x/W − 1) and back ((g + 1)·W − 1)/2, ≤ 4 roundings of values
    # ≤ 2W (≤ 8u·W px; the map changes by ≤ 8 per px), then blends ≤ 4 values ≤ 47 (3 roundings, and ≤ 3 more in
    # ``want``): |Δ| ≤ 8u·4·8 + 6u·47
    tol = dict(rtol=0.0, atol=U64 * (8 * 4 * 8 + 6 * 47))
    torch.testing.assert_close(out[0], maps[0, 0, 0], **tol)  # a pixel centre
    torch.testing.assert_close(out[1], 0.5 * (maps[0, 0, 0] + maps[0, 0, 1]), **tol)  # between two centres
    # (1.25, 1.75): x between columns 0 and 1 (t = 0.75), y between rows 1 and 2 (t = 0.25)
    m = maps[1]
    want = 0.75 * (0.25 * m[1, 0] + 0.75 * m[1, 1]) + 0.25 * (0.25 * m[2, 0] + 0.75 * m[2, 1])
    torch.testing.assert_close(out[2], want, **tol)
    torch.testing.assert_close(out[3], maps[1, 2, 3], **tol)
    torch.testing.assert_close(out[4], maps[0, 2, 0], **tol)  # outside: the border clamps


def test_identical_gaussians_give_zero_loss() -> None:
    m = _maps(2, 5, 6, 0)
    T1, _ = _poses(2, 1)
    xy1, _, batch, wts = _matches(2, 5, 6, 30, 2)
    out = mac_loss(m, m, xy1, xy1, batch, wts, T1, T1)
    assert float(out.loss) == 0.0  # (a) both views run the same operations on the same numbers: every term is 0


def test_terms_match_a_hand_computation() -> None:
    """Two single-pixel maps, identity poses: each term from its definition."""
    cfg = MACConfig(delta_pos=0.5, delta_shape=0.1)

    def one(mu, ls, op, sh):  # noqa: ANN001, ANN202
        t = lambda x: torch.tensor(x, dtype=D).reshape(1, 1, 1, -1)  # noqa: E731
        return _one_pixel(
            t(ls), means=t(mu), opacity_logits=torch.logit(t(op))[..., 0], sh=t(sh).reshape(1, 1, 1, 1, 3)
        )

    a = one([0.0, 0.0, 2.0], [0.0, -1.0, -2.0], 0.9, [0.1, 0.2, 0.3])
    b = one([0.1, -0.2, 2.0], [-2.0, 0.5, -1.0], 0.5, [0.0, 0.2, -0.3])
    T = torch.eye(4, dtype=D)[None]
    xy = torch.tensor([[0.5, 0.5]], dtype=D)
    out = mac_loss(a, b, xy, xy, torch.tensor([0]), torch.tensor([2.0], dtype=D), T, T, cfg)
    pos = 0.3**2 / (2 * 0.5)  # L1 distance 0.3 < δ = 0.5: quadratic part
    # sorted 2·log s: a → (-4, -2, 0), b → (-4, -2, 1): L1 = 1 ≥ δs → 1 − 0.05
    shape = 1.0 - 0.05
    app = 0.4 + (0.1 + 0.0 + 0.6)
    w = 2.0 / (2.0 + cfg.eps)
    # float64, ≤ 20 roundings a side plus logit/sigmoid/log (≤ 2 ulp each), no cancellation of inputs beyond
    # their own rounding: γ₃₂ relative
    rel = dict(rel=gamma(32, D), abs=0.0)
    assert float(out.position) == pytest.approx(w * pos, **rel)
    assert float(out.shape) == pytest.approx(w * shape, **rel)
    assert float(out.appearance) == pytest.approx(w * app, **rel)
    assert float(out.loss) == pytest.approx(w * (pos + 0.02 * shape + 0.1 * app), **rel)


def test_release_form_means_and_clamps_match_a_hand_computation() -> None:
    """``reduction="mean"`` with the release's clamps: position ‖Δμ‖₁/3, shape ‖Δ log λ‖₁/6 (the mean |Δ log σ|),
    colour mean |Δc|, each match's terms clamped; a second match far off hits every clamp."""
    cfg = MACConfig(delta_pos=0.05, delta_shape=0.05, reduction="mean", clamp_pos=1.0, clamp_shape=1.0,
                    clamp_opacity=1.0, clamp_colour=2.0)  # fmt: skip

    def one(mu, ls, op, sh):  # noqa: ANN001, ANN202
        t = lambda x: torch.tensor(x, dtype=D).reshape(1, 1, 2, -1)  # noqa: E731
        quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=D).repeat(1, 1, 2, 1)
        return GaussianMaps(t(mu), t(ls), quats, torch.logit(t(op))[..., 0], t(sh).reshape(1, 1, 2, 1, 3))

    # pixel 0: a near pair; pixel 1: 9 m apart, scales e⁴ apart, colours 5 apart (every clamp binds)
    a = one(
        [[0.0, 0.0, 2.0], [0.0, 0.0, 2.0]],
        [[0.0, -1.0, -2.0], [0.0, 0.0, 0.0]],
        [0.9, 0.5],
        [[0.1, 0.2, 0.3], [5.0, 5.0, 5.0]],
    )
    b = one(
        [[0.03, -0.06, 2.0], [3.0, 3.0, 5.0]],
        [[-2.0, 0.5, -1.0], [4.0, 4.0, 4.0]],
        [0.5, 0.5],
        [[0.0, 0.2, -0.3], [0.0, 0.0, 0.0]],
    )
    T = torch.eye(4, dtype=D)[None]
    xy = torch.tensor([[0.5, 0.5], [1.5, 0.5]], dtype=D)
    wts = torch.tensor([2.0, 1.0], dtype=D)
    out = mac_loss(a, b, xy, xy, torch.tensor([0, 0]), wts, T, T, cfg)
    pos0 = 0.03**2 / (2 * 0.05)  # mean |Δμ| = 0.09/3 = 0.03 < δ = 0.05: quadratic
    # sorted log λ = 2·log s: a → (-4, -2, 0), b → (-4, -2, 1): mean |Δ log σ| = (1/2)/3 ≥ δ → 1/6 − 0.025
    shape0 = 1.0 / 6.0 - 0.025
    app0 = 0.4 + (0.1 + 0.0 + 0.6) / 3.0
    pos1, shape1, app1 = 1.0, 1.0, 0.0 + 2.0  # Huber(3) and Huber(4) clamped at 1; colour mean 5 clamped at 2
    norm = 3.0 + cfg.eps
    rel = dict(rel=gamma(40, D), abs=0.0)  # as in the paper-form hand test, a few more roundings for the means
    assert float(out.position) == pytest.approx((2 * pos0 + pos1) / norm, **rel)
    assert float(out.shape) == pytest.approx((2 * shape0 + shape1) / norm, **rel)
    assert float(out.appearance) == pytest.approx((2 * app0 + app1) / norm, **rel)
    # the clamps stop the far match's gradient; the near one's still flows
    means = b.means.clone().requires_grad_(True)
    b2 = GaussianMaps(means, b.log_scales, b.quats, b.opacity_logits, b.sh)
    mac_loss(a, b2, xy, xy, torch.tensor([0, 0]), wts, T, T, cfg).loss.backward()
    assert torch.all(means.grad[0, 0, 1] == 0) and torch.any(means.grad[0, 0, 0] != 0)


def test_position_term_only_where_both_depths_are_positive() -> None:
    m1, m2 = _maps(1, 4, 4, 3), _maps(1, 4, 4, 4)
    m1.means[0, 0, 0, 2] = -1.0  # behind camera 1 at pixel (0, 0)
    T1, T2 = _poses(1, 5)
    xy = torch.tensor([[0.5, 0.5], [2.5, 2.5]], dtype=D)
    both = mac_loss(m1, m2, xy, xy, torch.tensor([0, 0]), torch.tensor([1.0, 0.0], dtype=D), T1, T2)
    assert float(both.position) == 0.0 and float(both.shape) > 0  # only the behind-camera match has weight


def test_world_translation_invariance_and_rotation_dependence() -> None:
    """Translating the world changes nothing; rotating it changes the L1 position term (the
    paper's definition), but not the shape and appearance terms."""
    m1, m2 = _maps(2, 5, 6, 6), _maps(2, 5, 6, 7)
    T1, T2 = _poses(2, 8)
    G = torch.eye(4, dtype=D)
    G[:3, :3] = quat_to_rotmat(torch.tensor([0.3, -0.2, 0.9, 0.1], dtype=D))
    G[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=D)
    xy1, xy2, batch, wts = _matches(2, 5, 6, 40, 9)
    a = mac_loss(m1, m2, xy1, xy2, batch, wts, T1, T2)
    b = mac_loss(m1, m2, xy1, xy2, batch, wts, G @ T1, G @ T2)
    # (a) from log-scales and opacities/SH: neither term reads the poses, the same operations on the same numbers
    assert torch.equal(a.shape, b.shape)
    assert torch.equal(a.appearance, b.appearance)
    assert abs(float(a.position) - float(b.position)) > 1e-3  # L1 is not rotation-invariant
    G[:3, :3] = torch.eye(3, dtype=D)
    c = mac_loss(m1, m2, xy1, xy2, batch, wts, G @ T1, G @ T2)
    # G·T adds g to each translation (one rounding of ≤ |t| + |g|), μ_w = Rμ + t' one more (of ≤ S, the largest
    # world coordinate), and g cancels in μ1 − μ2 only up to those: ≤ 4u·S per coordinate and view; the huber and
    # the weighted mean are 1-Lipschitz, and the weighted sums (≤ 40 terms) add γ₄₂ of the loss
    S = float(sum(x.abs().max() for x in (m1.means, m2.means)) * 3 + torch.cat([T1, T2])[:, :3, 3].abs().max())
    S += float(G[:3, 3].abs().max()) * 2
    tol = MACConfig().lambda_pos * 3 * 2 * 4 * U64 * S + gamma(42, D) * abs(float(a.loss))
    torch.testing.assert_close(a.loss, c.loss, rtol=0.0, atol=tol)


def test_scale_and_covariance_paths_agree() -> None:
    m1, m2 = _maps(2, 5, 6, 10), _maps(2, 5, 6, 11)
    T1, T2 = _poses(2, 12)
    xy1, xy2, batch, wts = _matches(2, 5, 6, 50, 13)
    # sample at pixel centres so both paths interpolate the same quantity (interpolating
    # log-scales and covariances differs between centres)
    xy1 = torch.floor(xy1) + 0.5
    xy2 = torch.floor(xy2) + 0.5
    a = mac_loss(m1, m2, xy1, xy2, batch, wts, T1, T2)
    b = mac_loss(m1, m2, xy1, xy2, batch, wts, T1, T2, covariances=(_cov(m1), _cov(m2)))
    # (b) float64, two routes to log λ: R S² Rᵀ (γ₅·λ_max per entry), the world rotation (γ₆·λ_max) and eigvalsh's
    # backward error (γ₉·λ_max, Householder + QR on 3×3) give |Δλ| ≤ γ₂₀·λ_max, so |Δ log λ| ≤ γ₂₀·κ with
    # κ = λ_max/λ_min of the Gaussian; 3 eigenvalues × 2 views per match, huber and weighted mean 1-Lipschitz
    ls = torch.cat([m1.log_scales, m2.log_scales])
    kappa = float(torch.exp(2 * (ls.max(-1).values - ls.min(-1).values)).max())
    shape_tol = 6 * gamma(20, D) * kappa + gamma(52, D) * abs(float(a.shape))
    torch.testing.assert_close(a.shape, b.shape, rtol=0.0, atol=shape_tol)
    loss_tol = MACConfig().lambda_shape * shape_tol + gamma(4, D) * abs(float(a.loss))  # the other terms: (a)
    torch.testing.assert_close(a.loss, b.loss, rtol=0.0, atol=loss_tol)


def test_no_matches_or_all_gated_out_is_exactly_zero_with_zero_gradients() -> None:
    m1, m2 = _maps(1, 4, 5, 14), _maps(1, 4, 5, 15)
    for t in (m1.means, m1.log_scales, m1.sh, m2.opacity_logits):
        t.requires_grad_(True)
    T1, T2 = _poses(1, 16)
    empty = torch.zeros(0, 2, dtype=D)
    out = mac_loss(m1, m2, empty, empty, torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=D), T1, T2)
    assert float(out.loss.detach()) == 0.0 and out.matches == 0
    out.loss.backward()
    for t in (m1.means, m1.log_scales, m1.sh, m2.opacity_logits):
        assert t.grad is not None and torch.equal(t.grad, torch.zeros_like(t))
        t.grad = None
    xy1, xy2, batch, _ = _matches(1, 4, 5, 10, 17)
    gated = mac_loss(m1, m2, xy1, xy2, batch, torch.zeros(10, dtype=D), T1, T2)
    assert float(gated.loss.detach()) == 0.0
    gated.loss.backward()
    for t in (m1.means, m1.log_scales, m1.sh, m2.opacity_logits):
        assert torch.isfinite(t.grad).all() and torch.equal(t.grad, torch.zeros_like(t))


@pytest.mark.parametrize("use_cov", [False, True])
def test_gradcheck_float64(use_cov: bool) -> None:
    m1, m2 = _maps(1, 3, 4, 18, k=1), _maps(1, 3, 4, 19, k=1)
    T1, T2 = _poses(1, 20)
    xy1, xy2, batch, wts = _matches(1, 3, 4, 6, 21)
    cfg = MACConfig(delta_pos=0.05, delta_shape=0.05)

    def fn(means1, ls1, op1, sh1, means2):  # noqa: ANN001, ANN202
        a = GaussianMaps(means=means1, log_scales=ls1, quats=m1.quats, opacity_logits=op1, sh=sh1)
        b = GaussianMaps(means2, m2.log_scales, m2.quats, m2.opacity_logits, m2.sh)
        cov = (_cov(a), _cov(b)) if use_cov else None
        return mac_loss(a, b, xy1, xy2, batch, wts, T1, T2, cfg, covariances=cov).loss

    inputs = [t.clone().requires_grad_(True) for t in (m1.means, m1.log_scales, m1.opacity_logits, m1.sh, m2.means)]
    assert torch.autograd.gradcheck(fn, inputs, eps=GC_EPS, atol=GC_ATOL, rtol=GC_RTOL)


@pytest.mark.parametrize(
    "eigs",
    [[2.0, 2.0, 2.0], [1.0, 3.0, 3.0], [1e-4, 1e-4, 5.0], [1e-12, 1e-12, 5.0], [0.5, 0.5, 0.5 + 1e-13]],
    ids=["isotropic", "disc", "needle", "extreme-needle", "nearly-isotropic"],
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_covariance_shape_term_is_stable_for_repeated_eigenvalues(eigs: list[float], dtype: torch.dtype) -> None:
    """Repeated eigenvalues (isotropic, disc and needle Gaussians, the usual initial state):
    the shape term and its gradient stay finite and equal the scale path's, where an
    eigendecomposition with eigenvectors would give NaN/inf gradients. The extreme needle
    (1e-12 against ‖Σ‖ = 5) is below what a covariance's entries resolve, so only
    finiteness is checked there."""
    R = quat_to_rotmat(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=D))
    ev = torch.tensor(eigs, dtype=D)
    cov = (R @ torch.diag(ev) @ R.T).to(dtype).reshape(1, 1, 1, 3, 3).requires_grad_(True)
    other = torch.tensor([0.2, 0.3, 0.4], dtype=dtype)
    base = dict(
        means=torch.tensor([[[[0.0, 0.0, 2.0]]]], dtype=dtype),
        opacity_logits=torch.zeros(1, 1, 1, dtype=dtype),
        sh=torch.zeros(1, 1, 1, 1, 3, dtype=dtype),
    )
    T = torch.eye(4, dtype=dtype)[None]
    xy = torch.tensor([[0.5, 0.5]], dtype=dtype)
    b = _one_pixel(0.5 * torch.log(other), **base)
    one = torch.ones(1, dtype=dtype)
    out = mac_loss(_one_pixel(**base), b, xy, xy, torch.tensor([0]), one, T, T, covariances=(cov, None))
    (g,) = torch.autograd.grad(out.shape, cov)
    assert torch.isfinite(g).all() and torch.isfinite(out.shape)
    if eigs[0] < 1e-8:
        return
    ref = _one_pixel((0.5 * torch.log(ev)).to(dtype), **base)
    want = mac_loss(ref, b, xy, xy, torch.tensor([0]), one, T, T)
    # Σ rounded to ``dtype`` (|E| ≤ u|Σ| entrywise, ‖E‖₂ ≤ √3·u‖Σ‖) and eigvalsh's backward error (γ₉‖Σ‖) move each
    # λᵢ by ≤ (√3u + γ₉)‖Σ‖, so log λᵢ by that over λᵢ (huber and |·| are 1-Lipschitz); the scale path rounds
    # 2·log s (≤ 2u|log λ|), and the sums add γ₈: 1e-3 relative ≈ 0.3× this bound for the float32 needle
    u = unit_roundoff(dtype)
    tol = (math.sqrt(3) * u + gamma(9, dtype)) * ev.max() * (1 / ev).sum() + 2 * u * ev.log().abs().sum()
    tol = float(tol) + gamma(8, dtype) * abs(float(want.shape))
    torch.testing.assert_close(out.shape, want.shape, rtol=0.0, atol=tol)
    # No contrast with ``torch.linalg.eigh``'s eigenvector gradient here: at an exactly repeated eigenvalue it
    # divides by λi − λj = 0, and what LAPACK returns there (inf, NaN or finite 1e14 values, by CPU kernel set)
    # is undefined behaviour, not a property of macsplat.


@pytest.mark.parametrize(("path", "smallest"), [("scales", 1e-12), ("covariances", 1e-10)])
def test_shape_gradient_scales_as_one_over_lambda(path: str, smallest: float) -> None:
    """The paper's claim: near degeneracy |∂L_shape/∂λ| ∝ 1/λ (log-log slope −1) as λ_min → 0.

    With scales, λ = s² exactly, checked down to λ = 1e-12. With raw covariances the
    eigenvalues come from the matrix entries, which resolve ~1e-16·‖Σ‖, so the check stops
    at 1e-10 (here ‖Σ‖ = 2)."""
    lams = [10.0 ** (-k) for k in range(2, round(-math.log10(smallest)) + 1, 2)]
    grads = []
    base = dict(means=torch.tensor([[[[0.0, 0.0, 2.0]]]], dtype=D), opacity_logits=torch.zeros(1, 1, 1, dtype=D),
                sh=torch.zeros(1, 1, 1, 1, 3, dtype=D))  # fmt: skip
    T = torch.eye(4, dtype=D)[None]
    xy = torch.tensor([[0.5, 0.5]], dtype=D)
    for lam in lams:
        ev1 = torch.tensor([lam, 1.0, 2.0], dtype=D).requires_grad_(True)
        ev2 = torch.tensor([10 * lam, 1.0, 2.0], dtype=D)
        cov = None
        if path == "scales":
            a, b = _one_pixel(0.5 * torch.log(ev1), **base), _one_pixel(0.5 * torch.log(ev2), **base)
        else:
            a, b = _one_pixel(**base), _one_pixel(**base)
            cov = (torch.diag_embed(ev1).reshape(1, 1, 1, 3, 3), torch.diag_embed(ev2).reshape(1, 1, 1, 3, 3))
        out = mac_loss(a, b, xy, xy, torch.tensor([0]), torch.ones(1, dtype=D), T, T, MACConfig(), covariances=cov)
        (g,) = torch.autograd.grad(out.shape, ev1)
        grads.append(abs(float(g[0])))
    slopes = [math.log(grads[i + 1] / grads[i]) / math.log(lams[i + 1] / lams[i]) for i in range(len(lams) - 1)]
    # The gradient is huber'·(1/λ) exactly (linear part of the huber), so the slope is −1 up to the gradient's
    # relative rounding: a few u on the scale path; through eigvalsh, γ₉·‖Σ‖/λ (λ down to 1e-10, ‖Σ‖ = 2).
    # Two gradients over log(100), plus the slope's own ratio, logs and quotient (4u) (measured: −1 ± 2.2e-16)
    rel_err = gamma(4, D) + (gamma(9, D) * 2.0 / lams[-1] if path == "covariances" else 0.0)
    assert all(s == pytest.approx(-1.0, abs=2 * rel_err / math.log(100) + 4 * U64) for s in slopes), slopes
    assert all(math.isfinite(g) and g > 0 for g in grads)


def test_non_finite_and_malformed_inputs_are_rejected() -> None:
    m1, m2 = _maps(1, 3, 3, 23), _maps(1, 3, 3, 24)
    T1, T2 = _poses(1, 25)
    xy1, xy2, batch, wts = _matches(1, 3, 3, 4, 26)
    bad = xy1.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="xy1"):
        mac_loss(m1, m2, bad, xy2, batch, wts, T1, T2)
    m1.sh[0, 0, 0, 0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="sh"):
        mac_loss(m1, m2, xy1, xy2, batch, wts, T1, T2)
    m1.sh[0, 0, 0, 0, 0] = 0.0
    with pytest.raises(InputError, match="weights"):
        mac_loss(m1, m2, xy1, xy2, batch, -wts, T1, T2)
    with pytest.raises(InputError, match="batch"):
        mac_loss(m1, m2, xy1, xy2, batch + 5, wts, T1, T2)


def test_transforms_default_to_the_maps_own_then_the_identity() -> None:
    """Without explicit transforms the loss uses each map's ``cam_to_world``, else the identity; the
    appearance term compares opacities ``sigmoid(logit)``, sampled after the sigmoid."""
    m1, m2 = _maps(2, 4, 5, 27), _maps(2, 4, 5, 28)
    T1, T2 = _poses(2, 29)
    xy1, xy2, batch, wts = _matches(2, 4, 5, 20, 30)
    want = mac_loss(m1, m2, xy1, xy2, batch, wts, T1, T2)
    posed = [GaussianMaps(*m.tensors(), cam_to_world=T) for m, T in ((m1, T1), (m2, T2))]
    got = mac_loss(posed[0], posed[1], xy1, xy2, batch, wts)
    for term in ("loss", "position", "shape", "appearance"):
        assert torch.equal(getattr(got, term), getattr(want, term))
    eye = torch.eye(4, dtype=D).repeat(2, 1, 1)
    assert torch.equal(
        mac_loss(m1, m2, xy1, xy2, batch, wts).loss, mac_loss(m1, m2, xy1, xy2, batch, wts, eye, eye).loss
    )
    # a single match at pixel centres: the appearance term is |α1 − α2| + ‖c1 − c2‖₁ with α = sigmoid(logit)
    xy = torch.tensor([[1.5, 2.5]], dtype=D)
    one = mac_loss(m1, m2, xy, xy, torch.tensor([1]), torch.ones(1, dtype=D))
    a1, a2 = torch.sigmoid(m1.opacity_logits[1, 2, 1]), torch.sigmoid(m2.opacity_logits[1, 2, 1])
    app = (a1 - a2).abs() + (m1.sh[1, 2, 1] - m2.sh[1, 2, 1]).abs().sum()
    # float64 at a pixel centre (exact bilinear weights): a sum of 13 absolute differences (γ₁₄ of the total) and
    # the division; the vectorised and the scalar sigmoid each ≤ 2 ulp of α ≤ 1 — γ₂₀ relative covers it all
    torch.testing.assert_close(one.appearance, app / (1 + MACConfig().eps), rtol=gamma(20, D), atol=0.0)
    with pytest.raises(InputError, match="covariances"):
        mac_loss(m1, m2, xy1, xy2, batch, wts, covariances=(torch.zeros(2, 4, 5, 3), None))


def test_huber() -> None:
    x = torch.tensor([0.0, 0.05, 0.1, 1.0, -2.0], dtype=D)
    # float64: ≤ 3 roundings of the decimal inputs, and the literals' own rounding: γ₄ relative (0 stays exact)
    torch.testing.assert_close(huber(x, 0.1), torch.tensor([0.0, 0.0125, 0.05, 0.95, 1.95], dtype=D),
                               rtol=gamma(4, D), atol=0.0)  # fmt: skip
