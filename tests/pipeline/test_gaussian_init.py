"""The per-pixel Gaussians' frames: the quaternion of each pixel's (tilt, cross, normal) frame."""

from __future__ import annotations

import numpy as np

from macsplat_cli.pipeline.gaussian_init import _frame_quats
from macsplat_cli.rotations import quat_to_rotmat_np, rotmat_to_quat_np


def test_frame_quaternions_are_bit_identical_to_the_general_conversion_on_every_branch() -> None:
    """Every Shepperd branch (random rotations take all four; the 180° turns about each axis force x, y, z), the
    all-zero frame of a pixel without depth, and NaN: the same bits as ``rotmat_to_quat_np``."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(4000, 4))
    R = quat_to_rotmat_np(q / np.linalg.norm(q, axis=1, keepdims=True))
    special = np.stack([np.zeros((3, 3)), np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]),
                        np.diag([-1.0, -1, 1]), np.full((3, 3), np.nan)])  # fmt: skip
    R = np.concatenate([R, special])
    t1, t2, n = (np.ascontiguousarray(R[:, :, c]) for c in range(3))
    general = rotmat_to_quat_np(np.stack([t1, t2, n], axis=2))
    trace = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    pivots = np.argmax(np.stack([trace, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], -1), -1)
    assert set(pivots[:4000].tolist()) == {0, 1, 2, 3}  # the random frames reach every branch
    ours = _frame_quats(t1, t2, n)
    assert ours.shape == general.shape == (len(R), 4)
    assert np.array_equal(ours.view(np.int64), general.view(np.int64))
