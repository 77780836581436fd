"""The Gaussians container and the SH basis."""

from __future__ import annotations

import math

import pytest
import torch

from macsplat_cli.errors import InputError, NonFiniteError, ShapeError
from macsplat_cli.gaussians import Gaussians, quat_to_rotmat
from macsplat_cli.sh import C0, eval_sh, rgb_to_sh0, sh0_to_rgb

from _helpers import random_gaussians


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
    torch.testing.assert_close(g.scales, scales)
    torch.testing.assert_close(g.opacities, op)
    torch.testing.assert_close(sh0_to_rgb(g.sh[:, 0]), rgb)
    assert torch.all(torch.isfinite(Gaussians.from_activated(means, scales * 0, quats, op * 0 + 1, rgb).opacity_logits))


def test_cat_select_and_covariance() -> None:
    a, b = random_gaussians(3, sh_degree=0), random_gaussians(2, seed=1, sh_degree=2)
    c = Gaussians.cat([a, b])
    assert len(c) == 5 and c.sh_degree == 2 and torch.all(c.sh[:3, 1:] == 0)
    assert torch.equal(c[torch.tensor([3, 4])].means, b.means)
    cov = c.covariances()
    R = c.rotations()
    expected = R @ torch.diag_embed(c.scales**2) @ R.transpose(-1, -2)
    torch.testing.assert_close(cov, expected)
    assert torch.all(torch.linalg.eigvalsh(cov) > 0)


def test_quat_to_rotmat_is_a_rotation_for_any_norm() -> None:
    q = torch.randn(100, 4, dtype=torch.float64) * torch.logspace(-5, 5, 100, dtype=torch.float64)[:, None]
    R = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(100, 3, 3)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(100, dtype=torch.float64))
    # a 90° turn about z maps x to y
    h = math.sqrt(0.5)
    Rz = quat_to_rotmat(torch.tensor([h, 0.0, 0.0, h], dtype=torch.float64))
    x_axis, y_axis = torch.eye(3, dtype=torch.float64)[:2]
    torch.testing.assert_close(Rz @ x_axis, y_axis)
    # zero quaternion: identity and zero gradient, not NaN
    z = torch.zeros(1, 4, requires_grad=True)
    R0 = quat_to_rotmat(z)
    R0.sum().backward()
    assert torch.equal(R0[0], torch.eye(3)) and torch.equal(z.grad, torch.zeros(1, 4))


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
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_dc_conversion() -> None:
    rgb = torch.tensor([[0.0, 0.5, 1.0]])
    torch.testing.assert_close(rgb_to_sh0(rgb), torch.tensor([[-0.5 / C0, 0.0, 0.5 / C0]]))
    torch.testing.assert_close(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)
