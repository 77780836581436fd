"""The Gaussians and GaussianMaps containers and the SH basis."""

from __future__ import annotations

import math

import pytest
import torch

from macsplat_cli.errors import InputError, NonFiniteError, ShapeError
from macsplat_cli.gaussians import GaussianMaps, Gaussians
from macsplat_cli.rotations import quat_to_rotmat
from macsplat_cli.sh import C0, eval_sh, rgb_to_sh0, sh0_to_rgb

from support.gaussians import random_gaussians
from support.numerics import ROT_MAT, ROT_QUAT, ROT_UNIT_Q, gamma, unit_roundoff

U32 = unit_roundoff(torch.float32)


def _params(n: int = 4, k: int = 1, dtype: torch.dtype = torch.float32) -> dict:
    return dict(
        means=torch.zeros(n, 3, dtype=dtype),
        log_scales=torch.zeros(n, 3, dtype=dtype),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dtype).repeat(n, 1),
        opacity_logits=torch.zeros(n, dtype=dtype),
        sh=torch.zeros(n, k, 3, dtype=dtype),
    )


@pytest.mark.parametrize(
    ("field", "bad", "match"),
    [
        ("means", torch.zeros(4, 2), "means has shape"),
        ("log_scales", torch.zeros(3, 3), "log_scales has shape"),
        ("quats", torch.zeros(4, 3), "quats has shape"),
        ("opacity_logits", torch.zeros(4, 1), "opacity_logits has shape"),
        ("sh", torch.zeros(4, 5, 3), "K in"),
        ("sh", torch.zeros(4, 25, 3), "K in"),  # degree 4 is not supported
    ],
)
def test_shape_validation(field: str, bad: torch.Tensor, match: str) -> None:
    p = _params()
    p[field] = bad
    with pytest.raises(ShapeError, match=match):
        Gaussians(**p)


def test_dtype_validation() -> None:
    p = _params()
    p["opacity_logits"] = torch.zeros(4, dtype=torch.float64)
    with pytest.raises(InputError, match="share one dtype"):
        Gaussians(**p)
    p = _params()
    p["means"] = torch.zeros(4, 3, dtype=torch.int64)
    with pytest.raises(InputError, match="floating-point"):
        Gaussians(**p)


def test_finiteness_is_checked_on_request() -> None:
    g = random_gaussians(5)
    g.check_finite()
    g.sh[2, 0, 1] = float("nan")
    g.quats[4, 0] = float("inf")
    assert g.finite_mask().tolist() == [True, True, False, True, False]
    with pytest.raises(NonFiniteError, match="quats"):
        g.check_finite()


def test_from_activated_round_trips_activations() -> None:
    means = torch.randn(6, 3)
    scales = torch.rand(6, 3) + 0.01
    quats = torch.randn(6, 4)
    op = torch.rand(6) * 0.9 + 0.05
    rgb = torch.rand(6, 3)
    g = Gaussians.from_activated(means, scales, quats, op, rgb, sh_degree=2)
    assert g.sh_degree == 2 and torch.all(g.sh[:, 1:] == 0)
    # float32: exp(log s): log to 1 ulp (2u·|log s| absolute) passed on by exp, plus exp's own ulp (2u)
    torch.testing.assert_close(g.scales, scales, rtol=(2 + 2 * float(scales.log().abs().max())) * U32, atol=0)
    # sigmoid(log op − log1p(−op)): the logit off by 2u(|log op| + |log(1 − op)|) + u|logit|, times sigmoid' / op
    # = 1 − op ≤ 1, and sigmoid's 2 ulps (4u)
    logit_err = 2 * (op.log().abs() + (-op).log1p().abs()) + (op.log() - (-op).log1p()).abs()
    torch.testing.assert_close(g.opacities, op, rtol=float(logit_err.max() + 4) * U32, atol=0)
    # (x − 0.5)/C0·C0 + 0.5: 4 roundings of values ≤ 1
    torch.testing.assert_close(sh0_to_rgb(g.sh[:, 0]), rgb, rtol=0, atol=4 * U32)
    assert torch.all(torch.isfinite(Gaussians.from_activated(means, scales * 0, quats, op * 0 + 1, rgb).opacity_logits))


def test_cat_select_and_covariance() -> None:
    a, b = random_gaussians(3, sh_degree=0), random_gaussians(2, seed=1, sh_degree=2)
    c = Gaussians.cat([a, b])
    assert len(c) == 5 and c.sh_degree == 2 and torch.all(c.sh[:3, 1:] == 0)
    assert torch.equal(c[torch.tensor([3, 4])].means, b.means)
    cov = c.covariances()
    R = c.rotations()
    expected = R @ torch.diag_embed(c.scales**2) @ R.transpose(-1, -2)
    # (b) (R·s)(R·s)ᵀ vs R·diag(s²)·Rᵀ with the same R: 3-term sums of products ≤ s² each (γ₃) plus the products'
    # roundings (2u), each side
    tol = 2 * (gamma(3, torch.float32) + 2 * U32) * float(c.scales.max()) ** 2
    torch.testing.assert_close(cov, expected, rtol=0, atol=tol)
    assert torch.all(torch.linalg.eigvalsh(cov) > 0)


def test_sh_basis_is_orthonormal_on_the_sphere() -> None:
    """∫ Y_i Y_j dΩ = δ_ij: checks every constant and sign pattern of the degree-3 basis."""
    n = 200_000
    k = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * k / n)
    theta = math.pi * (1 + 5**0.5) * k
    dirs = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], -1)
    basis = []
    for i in range(16):  # Y_i(dir) by evaluating a one-hot coefficient (minus the +0.5 offset)
        sh = torch.zeros(n, 16, 3, dtype=torch.float64)
        sh[:, i, 0] = 1.0
        basis.append(eval_sh(sh, dirs)[:, 0] - 0.5)
    Y = torch.stack(basis, -1)
    gram = Y.T @ Y * (4 * math.pi / n)
    # (d) quadrature, not rounding: the spherical Fibonacci rule integrates these degree ≤ 6 products to 1.4e-7
    # (measured; float64 rounding of the 200 000-term sums ≤ γ₂₀₀₀₀₀·1 ≈ 2e-11): 1e-5 leaves 70× and still fails
    # for a basis constant wrong in its 5th digit
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-5, rtol=0)


def test_dc_conversion() -> None:
    rgb = torch.tensor([[0.0, 0.5, 1.0]])
    # float32 ±0.5/fl(C0) against fl(±0.5/C0): C0's rounding and the quotient's (2u)
    torch.testing.assert_close(rgb_to_sh0(rgb), torch.tensor([[-0.5 / C0, 0.0, 0.5 / C0]]), rtol=2 * U32, atol=0)
    torch.testing.assert_close(sh0_to_rgb(rgb_to_sh0(rgb)), rgb, rtol=0, atol=4 * U32)  # 4 roundings of values ≤ 1


# ------------------------------------------------------------------------------ GaussianMaps
D = torch.float64


def _random_maps(b: int, h: int, w: int, seed: int, valid: torch.Tensor | None = None, *, pose: bool = True,
                 k: int = 1) -> GaussianMaps:  # fmt: skip
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=D).repeat(b, 1, 1)
    T[:, :3, :3] = quat_to_rotmat(torch.randn(b, 4, generator=g, dtype=D))
    T[:, :3, 3] = torch.randn(b, 3, generator=g, dtype=D)
    means = torch.randn(b, h, w, 3, generator=g, dtype=D)
    means[..., 2] += 4
    return GaussianMaps(
        means=means,
        log_scales=torch.randn(b, h, w, 3, generator=g, dtype=D) - 3,
        quats=torch.randn(b, h, w, 4, generator=g, dtype=D),
        opacity_logits=torch.randn(b, h, w, generator=g, dtype=D) * 20,
        sh=torch.randn(b, h, w, k, 3, generator=g, dtype=D),
        valid=valid,
        cam_to_world=T if pose else None,
    )


def _map_params(b: int = 2, h: int = 3, w: int = 4) -> dict:
    m = _random_maps(b, h, w, 0)
    return dict(zip(["means", "log_scales", "quats", "opacity_logits", "sh"], m.tensors()))


@pytest.mark.parametrize(
    ("field", "bad", "error", "match"),
    [
        ("means", torch.zeros(2, 3, 4), ShapeError, "means has shape"),
        ("log_scales", torch.zeros(2, 3, 5, 3, dtype=D), ShapeError, "log_scales has shape"),
        ("quats", torch.zeros(2, 3, 4, 3, dtype=D), ShapeError, "quats has shape"),
        ("opacity_logits", torch.zeros(2, 3, 4, 1, dtype=D), ShapeError, "opacity_logits has shape"),
        ("sh", torch.zeros(2, 3, 4, 5, 3, dtype=D), ShapeError, "K in"),
        ("sh", torch.zeros(2, 3, 4, 3, dtype=D), ShapeError, "sh has shape"),  # colour-major [3, K] is not accepted
        ("valid", torch.ones(1, 3, 4, dtype=torch.bool), ShapeError, "valid has shape"),
        ("valid", torch.ones(2, 3, 4), InputError, "bool"),
        ("cam_to_world", torch.eye(4, dtype=D), ShapeError, "cam_to_world has shape"),
        ("cam_to_world", torch.eye(4, dtype=torch.int64).repeat(2, 1, 1), InputError, "floating-point"),
        ("opacity_logits", torch.zeros(2, 3, 4, dtype=torch.float32), InputError, "share one dtype"),
    ],
)
def test_maps_validation(field: str, bad: torch.Tensor, error: type, match: str) -> None:
    p = _map_params()
    GaussianMaps(**p)
    p[field] = bad
    with pytest.raises(error, match=match):
        GaussianMaps(**p)


def test_to_gaussians_moves_means_and_rotations_into_the_world_frame() -> None:
    valid = torch.tensor([[[True, False, True], [True, True, False]], [[False, False, False], [True, True, True]]])
    m = _random_maps(2, 2, 3, 0, valid, k=4)
    g = m.to_gaussians()
    assert len(g) == int(valid.sum()) == 7 and g.sh_degree == 1
    start = 0
    for b in range(2):
        n = int(valid[b].sum())
        part = g[slice(start, start + n)]
        start += n
        R, t = m.cam_to_world[b, :3, :3], m.cam_to_world[b, :3, 3]
        mu = m.means[b][valid[b]]
        # float64 Rμ + t in two orders: γ₄·(|R||μ| + |t|) each
        bound = 2 * gamma(4, D) * (mu.abs() @ R.abs().T + t.abs())
        assert ((part.means - (mu @ R.T + t)).abs() <= bound).all()
        # R → q (Shepperd, ROT_QUAT), q ⊗ q' (γ₄ relative), back to R (ROT_MAT; a rotation by ≤ 2‖δq‖), against
        # R·R(q') (ROT_MAT twice, γ₃)
        rot_tol = (2 * math.sqrt(2) * 2 * (ROT_QUAT + 4) + 3 * ROT_MAT + 3) * unit_roundoff(D)
        torch.testing.assert_close(quat_to_rotmat(part.quats), R @ quat_to_rotmat(m.quats[b][valid[b]]), rtol=0,
                                   atol=rot_tol)  # fmt: skip
        # rotation does not change the other parameters: copied bit for bit
        assert torch.equal(part.log_scales, m.log_scales[b][valid[b]])
        assert torch.equal(part.opacity_logits, m.opacity_logits[b][valid[b]])
        assert torch.equal(part.sh, m.sh[b][valid[b]])
    # the same as converting view by view
    views = Gaussians.cat([m.view(b).to_gaussians() for b in range(2)])
    for x, y in zip(g.tensors(), views.tensors()):
        assert torch.equal(x, y)


def test_to_gaussians_is_lossless_and_round_trips_with_the_identity_camera() -> None:
    """No activation round trip: opacity logits of ±40, any quaternion norm, come back bit for bit."""
    m = _random_maps(2, 3, 4, 1, pose=False)
    m.opacity_logits[0, 0, :2] = torch.tensor([40.0, -40.0], dtype=D)
    m.quats[1, 2, 3] *= 1e-3
    for cam in (None, torch.eye(4, dtype=D).repeat(2, 1, 1)):
        g = GaussianMaps(*m.tensors(), cam_to_world=cam).to_gaussians()
        assert len(g) == 2 * 3 * 4
        back = GaussianMaps(*(t.reshape(2, 3, 4, *t.shape[1:]) for t in g.tensors()))
        for x, y in zip(back.tensors(), m.tensors()):
            assert torch.equal(x, y)


def test_to_gaussians_is_differentiable() -> None:
    m = _random_maps(1, 2, 2, 2, torch.tensor([[[True, False], [True, True]]]))
    for t in m.tensors():
        t.requires_grad_(True)
    g = m.to_gaussians()
    sum(t.sum() for t in g.tensors()).backward()
    for t in m.tensors():
        assert t.grad is not None and t.grad.abs().sum() > 0
        assert torch.equal(t.grad[0, 0, 1], torch.zeros_like(t.grad[0, 0, 1]))  # the invalid pixel


def test_view_cat_and_properties() -> None:
    a = _random_maps(2, 3, 4, 3, torch.rand(2, 3, 4) > 0.5, k=1)
    b = _random_maps(1, 3, 4, 4, pose=False, k=4)
    assert a.batch == 2 and a.size == (3, 4) and a.sh_degree == 0 and a.dtype == D
    v = a.view(1)
    assert v.batch == 1 and torch.equal(v.means[0], a.means[1]) and torch.equal(v.valid[0], a.valid[1])
    assert torch.equal(a.view(-1).cam_to_world, a.cam_to_world[1:])
    with pytest.raises(IndexError):
        a.view(2)
    c = GaussianMaps.cat([a, b])
    assert c.batch == 3 and c.sh_degree == 1 and torch.all(c.sh[:2, :, :, 1:] == 0)
    assert torch.equal(c.valid[2], torch.ones(3, 4, dtype=torch.bool))  # b had every pixel
    assert torch.equal(c.cam_to_world[2], torch.eye(4, dtype=D)) and torch.equal(c.cam_to_world[:2], a.cam_to_world)
    assert GaussianMaps.cat([b, b]).valid is None and GaussianMaps.cat([b, b]).cam_to_world is None
    with pytest.raises(InputError, match="sizes"):
        GaussianMaps.cat([a, _random_maps(1, 4, 3, 5)])
    assert torch.equal(b.valid_mask(), torch.ones(1, 3, 4, dtype=torch.bool))


def test_pooled_averages_the_valid_pixels_of_each_block() -> None:
    valid = torch.ones(2, 4, 4, dtype=torch.bool)
    valid[0, 0, 1] = False  # block (0, 0) averages 3 pixels
    valid[0, 2:, 2:] = False  # block (1, 1) is empty
    m = _random_maps(2, 4, 4, 1, valid)
    p = m.pooled(2)
    assert p.size == (2, 2) and p.batch == 2
    assert p.valid[0].tolist() == [[True, True], [True, False]] and bool(p.valid[1].all())
    block = m.means[0, :2, :2][valid[0, :2, :2]]

    # float64 means of ≤ 4 values: avg_pool2d's masked sum and ÷ count (γ₅) against the test's mean (γ₄), of the
    # largest |value|; + log 2 one more rounding
    def tol(x: torch.Tensor) -> dict:
        return dict(rtol=0, atol=(gamma(5, D) + gamma(4, D) + unit_roundoff(D)) * float(x.abs().max() + 1))

    torch.testing.assert_close(p.means[0, 0, 0], block.mean(0), **tol(block))
    ls = m.log_scales[0, :2, :2][valid[0, :2, :2]]
    torch.testing.assert_close(p.log_scales[0, 0, 0], ls.mean(0) + math.log(2), **tol(ls))
    torch.testing.assert_close(p.sh[0, 1, 0], m.sh[0, 2:, :2].reshape(4, 1, 3).mean(0), **tol(m.sh[0, 2:, :2]))
    ol = m.opacity_logits[1, 2:, 2:]
    torch.testing.assert_close(p.opacity_logits[1, 1, 1], ol.mean(), **tol(ol))
    # a normalised quaternion, measured by the test's own norm (3u)
    torch.testing.assert_close(torch.linalg.vector_norm(p.quats[0, 0, 0]), torch.tensor(1.0, dtype=D), rtol=0,
                               atol=(ROT_UNIT_Q + 3) * unit_roundoff(D))  # fmt: skip
    assert torch.equal(p.cam_to_world, m.cam_to_world)
    # B views pool as each view alone
    for b in range(2):
        for x, y in zip(p.view(b).tensors(), m.view(b).pooled(2).tensors()):
            assert torch.equal(x, y)
    assert m.pooled(1) is m
    everything = _random_maps(1, 4, 4, 2, pose=False).pooled(2)
    assert everything.valid is None
    with pytest.raises(ValueError, match="pooled"):
        _random_maps(1, 3, 4, 2).pooled(2)


def test_maps_detach_clones_and_to_converts() -> None:
    m = _random_maps(1, 2, 3, 6, torch.ones(1, 2, 3, dtype=torch.bool))
    m.means.requires_grad_(True)
    d = m.detach()
    assert not d.means.requires_grad and d.means.data_ptr() != m.means.data_ptr()
    d.means.add_(1.0)  # optimising the copy leaves the original alone
    assert not torch.equal(d.means, m.means)
    f = m.to(dtype=torch.float32)
    assert all(t.dtype == torch.float32 for t in f.tensors())
    assert f.valid.dtype == torch.bool and f.cam_to_world.dtype == D
    m.detach().check_finite()
    bad = m.detach()
    bad.opacity_logits[0, 1, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="opacity_logits"):
        bad.check_finite()
