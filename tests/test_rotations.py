"""Quaternion ↔ rotation-matrix converters (macsplat_cli.rotations): NumPy and torch, (w, x, y, z)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from macsplat_cli.rotations import quat_multiply, quat_to_rotmat, quat_to_rotmat_np, rotmat_to_quat, rotmat_to_quat_np

from support.numerics import ROT_MAT, ROT_QUAT, ROT_ROUND_TRIP, ROT_UNIT_Q, gamma, unit_roundoff

D = torch.float64
U64 = unit_roundoff(np.float64)
# Float64 error budgets (first order; u = 2⁻⁵³; the ROT_* constants of support.numerics, derived here):
# * a unit quaternion q/‖q‖: the dot (γ₄, halved by the √), the √ and the ÷: ≤ 4u per component, ‖q̂‖ − 1 ≤ 4u;
# * R(q̂) (entries 1 − 2(y² + z²), 2(xy − wz), …, or I + s·(…) with s = 2/‖q‖²): ≤ 8u per entry (entries ≤ 1),
#   plus 2·ε for a q̂ of squared norm 1 + ε, so R is a rotation up to E_R ≤ 16u per entry;
# * Shepperd's R → q: the largest radicand 1 ± m₀₀ ± m₁₁ ± m₂₂ ≥ 1 carries ≤ 12u, s = 2√· ≤ 7u relative, the other
#   components (mᵢⱼ ± mⱼᵢ)/s ≤ 9u, the normalisation 4u: ≤ 13u per component, plus E_R passed on with gain ≤ 1;
# * R(q) from a q off by δ: a rotation by ≤ 2‖δ‖, so ≤ 2√2‖δ‖ per entry (‖δ‖ ≤ 2·max|δᵢ| for 4 components).
UNIT_Q = ROT_UNIT_Q * U64
ROTMAT = ROT_MAT * U64
QUAT = ROT_QUAT * U64
ROUND_TRIP = ROT_ROUND_TRIP * U64  # R → q → R


def _rotations(n: int, seed: int) -> np.ndarray:
    """Random rotations plus the hard cases: the identity and 180° turns (w = 0). [n + 6, 3, 3]"""
    q = np.random.default_rng(seed).normal(size=(n, 4))
    R = quat_to_rotmat_np(q)
    axes = [np.eye(3)[i] for i in range(3)] + [np.array([1.0, 1.0, 0.0]) / math.sqrt(2), np.ones(3) / math.sqrt(3)]
    return np.concatenate([R, np.eye(3)[None], np.stack([2 * np.outer(a, a) - np.eye(3) for a in axes])])


# ------------------------------------------------------------------------------------ NumPy
def test_numpy_round_trip_sign_and_norm_batched() -> None:
    R = _rotations(300, 0)
    q = rotmat_to_quat_np(R)
    assert q.shape == (306, 4) and q.dtype == np.float64
    assert np.all(q[:, 0] >= 0)
    # ‖q̂‖ − 1 ≤ 4u, and the test's own norm (γ₄/2 + u ≤ 3u)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=UNIT_Q + 3 * U64)
    np.testing.assert_allclose(quat_to_rotmat_np(q), R, rtol=0, atol=ROUND_TRIP)
    # (a) one matrix at a time gives the same bits as the batch: elementwise IEEE operations, and the norm's dot is
    # NumPy's matmul loop calling the same 4-term dot kernel for each matrix; any leading shape works
    for k in (0, 7, 300, 305):
        assert np.array_equal(rotmat_to_quat_np(R[k]), q[k])
    assert np.array_equal(rotmat_to_quat_np(R[:6].reshape(2, 3, 3, 3)), q[:6].reshape(2, 3, 4))
    assert rotmat_to_quat_np(np.zeros((0, 3, 3))).shape == (0, 4)
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 3\]"):
        rotmat_to_quat_np(np.eye(4))


def test_numpy_quat_to_rotmat_normalises_and_q_equals_minus_q() -> None:
    q = np.random.default_rng(1).normal(size=(50, 4))
    R = quat_to_rotmat_np(q)
    # R Rᵀ: 3-term dots of entries each ≤ ROTMAT off a rotation's: ≤ 2·3·ROTMAT + γ₃; det (LU, 3×3): ≤ 3·ROTMAT·3 + γ₆
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), eye, rtol=0, atol=6 * ROTMAT + gamma(3, np.float64))
    np.testing.assert_allclose(np.linalg.det(R), 1.0, rtol=0, atol=9 * ROTMAT + gamma(6, np.float64))
    # −3q normalises to −q̂ up to 2·UNIT_Q per component: R moves by ≤ 2√2·2·(2·UNIT_Q), plus both R's roundings
    np.testing.assert_allclose(quat_to_rotmat_np(-3.0 * q), R, rtol=0,
                               atol=2 * math.sqrt(2) * 4 * UNIT_Q + 2 * ROTMAT)  # fmt: skip
    # Shepperd on R (QUAT) against q normalised by the test (UNIT_Q + 3u)
    np.testing.assert_allclose(rotmat_to_quat_np(R), q / np.linalg.norm(q, axis=1, keepdims=True) * np.sign(q[:, :1]),
                               rtol=0, atol=QUAT + UNIT_Q + 3 * U64)  # fmt: skip


# ------------------------------------------------------------------------------------ torch
def test_quat_to_rotmat_is_a_rotation_for_any_norm() -> None:
    q = torch.randn(100, 4, dtype=torch.float64) * torch.logspace(-5, 5, 100, dtype=torch.float64)[:, None]
    R = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(100, 3, 3)
    # s = 2/‖q‖² is scale-free (γ₅ relative whatever ‖q‖ is), so R is within ROTMAT of a rotation at any norm
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=6 * ROTMAT + gamma(3, D))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(100, dtype=D), rtol=0, atol=9 * ROTMAT + gamma(6, D))
    # a 90° turn about z maps x to y
    h = math.sqrt(0.5)
    Rz = quat_to_rotmat(torch.tensor([h, 0.0, 0.0, h], dtype=torch.float64))
    x_axis, y_axis = torch.eye(3, dtype=torch.float64)[:2]
    torch.testing.assert_close(Rz @ x_axis, y_axis, rtol=0, atol=ROTMAT + gamma(3, D))
    # zero quaternion: identity and zero gradient, not NaN
    z = torch.zeros(1, 4, requires_grad=True)
    R0 = quat_to_rotmat(z)
    R0.sum().backward()
    assert torch.equal(R0[0], torch.eye(3)) and torch.equal(z.grad, torch.zeros(1, 4))


def test_torch_and_numpy_converters_agree() -> None:
    R = _rotations(200, 2)
    q_np = rotmat_to_quat_np(R)
    q_t = rotmat_to_quat(torch.from_numpy(R))
    assert q_t.dtype == D and bool((q_t[:, 0] >= 0).all())
    # (b) the twins share every elementwise operation; only the norm's 4-term dot may run in another order (ATen
    # bmm vs NumPy's), ≤ 3u each way, so the normalised quaternions differ by ≤ 2·3u + 2u (the ÷ of unequal inputs)
    torch.testing.assert_close(q_t, torch.from_numpy(q_np), rtol=0, atol=8 * U64)
    # two formulas (I + s·(…) vs 1 − 2(y² + z²)), each ≤ ROTMAT, from quaternions ≤ 8u apart (≤ 2√2·16u)
    torch.testing.assert_close(quat_to_rotmat(q_t), torch.from_numpy(quat_to_rotmat_np(q_np)), rtol=0,
                               atol=2 * ROTMAT + 2 * math.sqrt(2) * 16 * U64)  # fmt: skip
    assert torch.equal(rotmat_to_quat(R), q_t)  # (a) an array is accepted as is: the same operations, same numbers
    q32 = rotmat_to_quat(torch.from_numpy(R).float())
    assert q32.dtype == torch.float32
    # (c) the float32 round trip against the float64 rotation: the same budget as ROUND_TRIP in units of u32, plus
    # the rounding of R to float32 (u32 per entry, passed on with gain ≤ 1 by both steps)
    torch.testing.assert_close(quat_to_rotmat(q32).double(), torch.from_numpy(R), rtol=0,
                               atol=(ROT_ROUND_TRIP + 2) * unit_roundoff(torch.float32))  # fmt: skip


def test_quat_multiply_composes_rotations() -> None:
    g = torch.Generator().manual_seed(3)
    a, b = torch.randn(20, 4, generator=g, dtype=D), torch.randn(20, 4, generator=g, dtype=D)
    # R(ab): ab is 4-term sums (γ₄ relative to ‖a‖‖b‖, a rotation error ≤ 2√2·2γ₄) and R's ROTMAT; R(a)R(b):
    # 3-term dots of two ROTMAT-accurate rotations (≤ 2·3·ROTMAT + γ₃)
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), rtol=0,
                               atol=2 * math.sqrt(2) * 2 * gamma(4, D) + 7 * ROTMAT + gamma(3, D))  # fmt: skip
    one = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=D).expand(20, 4)
    assert torch.equal(quat_multiply(one, b), b) and torch.equal(quat_multiply(b, one), b)  # products by 1 and 0
    conj = a * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=D)
    n2 = (a * a).sum(-1)
    # every component is a 4-term sum of products |aᵢaⱼ| whose absolute sum is ≤ 2‖a‖²: ≤ γ₄·2‖a‖² each, and the
    # test's own n2 in another order (γ₄‖a‖²)
    torch.testing.assert_close(quat_multiply(a, conj), torch.stack([n2, *[torch.zeros_like(n2)] * 3], -1), rtol=0,
                               atol=3 * gamma(4, D) * float(n2.max()))  # fmt: skip
    # not commutative: a 90° turn about x then about y differs from the reverse
    h = math.sqrt(0.5)
    qx, qy = torch.tensor([h, h, 0.0, 0.0], dtype=D), torch.tensor([h, 0.0, h, 0.0], dtype=D)
    assert not torch.allclose(quat_multiply(qx, qy), quat_multiply(qy, qx))


def test_nearest_rotation_projects_onto_so3() -> None:
    """A rotation perturbed by 1e-9 comes back a rotation to a few u and within ~1e-9 of it; a reflection comes
    back a rotation (det +1); batches work."""
    from macsplat_cli.rotations import nearest_rotation

    u = np.finfo(np.float64).eps / 2
    rng = np.random.default_rng(4)
    q = rng.normal(size=(5, 4))
    R = quat_to_rotmat_np(q / np.linalg.norm(q, axis=1, keepdims=True))
    noisy = R + 1e-9 * rng.normal(size=R.shape)
    out = nearest_rotation(noisy)
    eye = np.broadcast_to(np.eye(3), out.shape)
    # LAPACK's U and V are orthonormal to a small multiple of n·u (3·3u each, n = 3); U·Vᵀ and the check's own
    # product add γ₃ each: 9u + 9u + 2γ₃
    assert np.abs(out @ out.transpose(0, 2, 1) - eye).max() <= 18 * u + 2 * 3 * u / (1 - 3 * u)
    assert np.abs(out - R).max() <= 1e-8
    flipped = nearest_rotation(np.diag([1.0, 1.0, -1.0]))
    assert np.linalg.det(flipped) == pytest.approx(1.0, abs=8 * u)
