"""Quaternion ↔ rotation-matrix converters (macsplat_cli.rotations): NumPy and torch, (w, x, y, z)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from macsplat_cli.rotations import quat_multiply, quat_to_rotmat, quat_to_rotmat_np, rotmat_to_quat, rotmat_to_quat_np

D = torch.float64


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
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(quat_to_rotmat_np(q), R, atol=1e-12)
    # one matrix at a time gives the same bits as the batch; any leading shape works
    for k in (0, 7, 300, 305):
        assert np.array_equal(rotmat_to_quat_np(R[k]), q[k])
    assert np.array_equal(rotmat_to_quat_np(R[:6].reshape(2, 3, 3, 3)), q[:6].reshape(2, 3, 4))
    assert rotmat_to_quat_np(np.zeros((0, 3, 3))).shape == (0, 4)
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 3\]"):
        rotmat_to_quat_np(np.eye(4))


def test_numpy_quat_to_rotmat_normalises_and_q_equals_minus_q() -> None:
    q = np.random.default_rng(1).normal(size=(50, 4))
    R = quat_to_rotmat_np(q)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(quat_to_rotmat_np(-3.0 * q), R, atol=1e-14)
    np.testing.assert_allclose(rotmat_to_quat_np(R), q / np.linalg.norm(q, axis=1, keepdims=True) * np.sign(q[:, :1]),
                               atol=1e-12)  # fmt: skip


# ------------------------------------------------------------------------------------ torch
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


def test_torch_and_numpy_converters_agree() -> None:
    R = _rotations(200, 2)
    q_np = rotmat_to_quat_np(R)
    q_t = rotmat_to_quat(torch.from_numpy(R))
    assert q_t.dtype == D and bool((q_t[:, 0] >= 0).all())
    torch.testing.assert_close(q_t, torch.from_numpy(q_np), rtol=0, atol=1e-15)
    torch.testing.assert_close(quat_to_rotmat(q_t), torch.from_numpy(quat_to_rotmat_np(q_np)), rtol=0, atol=1e-14)
    assert torch.equal(rotmat_to_quat(R), q_t)  # an array is accepted as is
    q32 = rotmat_to_quat(torch.from_numpy(R).float())
    assert q32.dtype == torch.float32
    torch.testing.assert_close(quat_to_rotmat(q32).double(), torch.from_numpy(R), rtol=0, atol=1e-6)


def test_quat_multiply_composes_rotations() -> None:
    g = torch.Generator().manual_seed(3)
    a, b = torch.randn(20, 4, generator=g, dtype=D), torch.randn(20, 4, generator=g, dtype=D)
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b))
    one = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=D).expand(20, 4)
    assert torch.equal(quat_multiply(one, b), b) and torch.equal(quat_multiply(b, one), b)
    conj = a * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=D)
    n2 = (a * a).sum(-1)
    torch.testing.assert_close(quat_multiply(a, conj), torch.stack([n2, *[torch.zeros_like(n2)] * 3], -1))
    # not commutative: a 90° turn about x then about y differs from the reverse
    h = math.sqrt(0.5)
    qx, qy = torch.tensor([h, h, 0.0, 0.0], dtype=D), torch.tensor([h, 0.0, h, 0.0], dtype=D)
    assert not torch.allclose(quat_multiply(qx, qy), quat_multiply(qy, qx))
