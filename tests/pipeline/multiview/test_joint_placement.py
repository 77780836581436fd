"""Issue 40: the joint refinement places each map's Gaussians for a photo by one composed rigid motion
(:func:`packed.placements`, :func:`packed.placed`), the same Gaussians as the three motions one after another (the
registered pose, the camera's update, the photo camera's inverse update) up to the rounding, the same gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from macsplat_cli.gaussians import GaussianMaps, Gaussians
from macsplat_cli.pipeline.multiview import joint, packed
from macsplat_cli.rotations import quat_multiply, quat_to_rotmat


def _pose(g: torch.Generator) -> np.ndarray:
    """A random rigid camera-to-world. [4, 4]"""
    q = torch.randn(4, generator=g, dtype=torch.float64)
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(q).numpy()
    T[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64).numpy()
    return T


def _leaves(n: int, T: np.ndarray, g: torch.Generator, dtype: torch.dtype) -> GaussianMaps:
    """A packed one-row map of ``n`` random Gaussians (SH degree 1) at pose ``T``, its tensors leaves."""
    t = [torch.randn(1, 1, n, *s, generator=g, dtype=torch.float64).to(dtype).requires_grad_(True)
         for s in ((3,), (3,), (4,), (), (4, 3))]  # fmt: skip
    return GaussianMaps(*t, cam_to_world=torch.as_tensor(T)[None])


def _three_motions(params: list[GaussianMaps], chosen: list, poses: joint._Poses, k: int) -> Gaussians:
    """The placement as the refinement did it before issue 40: each map to the world by its pose
    (``to_gaussians``), moved with its camera's update, then placed for photo ``k``'s unrefined camera."""
    q, c = poses.current()
    parts = []
    for j, (m, sel) in enumerate(zip(params, chosen)):
        if sel is None:
            continue
        if isinstance(sel, torch.Tensor):
            mask = torch.zeros(m.means.shape[:3], dtype=torch.bool)
            mask[0, 0, sel] = True
            m = GaussianMaps(*m.tensors(), valid=mask, cam_to_world=m.cam_to_world)
        w = m.to_gaussians()
        qj = q[j].to(w.dtype)
        means = (w.means - poses.c0[j].to(w.dtype)) @ quat_to_rotmat(qj).T + c[j].to(w.dtype)
        parts.append(Gaussians(means, w.log_scales, quat_multiply(qj.expand(len(w), 4), w.quats), w.opacity_logits,
                               w.sh))  # fmt: skip
    world = Gaussians.cat(parts)
    if k == poses.fixed:
        return world
    qi = packed.conj(q[k]).to(world.dtype)
    means = (world.means - c[k].to(world.dtype)) @ quat_to_rotmat(qi).T + poses.c0[k].to(world.dtype)
    quats = quat_multiply(qi.expand(len(world), 4), world.quats)
    return Gaussians(means, world.log_scales, quats, world.opacity_logits, world.sh)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("k", [0, 2])
def test_one_composed_motion_places_the_gaussians_as_three(dtype: torch.dtype, k: int) -> None:
    g = torch.Generator().manual_seed(7)
    Ts = [_pose(g) for _ in range(3)]
    params = [_leaves(n, T, g, dtype) for n, T in zip((6, 5, 4), Ts)]
    poses = joint._Poses(Ts, fixed=0)
    with torch.no_grad():
        poses.omega.copy_(0.05 * torch.randn(3, 3, generator=g, dtype=torch.float64))
        poses.delta.copy_(0.1 * torch.randn(3, 3, generator=g, dtype=torch.float64))
    chosen = [torch.tensor([0, 2, 3]), None, True]  # a subset, a map the photo does not see, all
    q, c = poses.current()
    motion = packed.placements(packed.frames_of(params), q, c, poses.c0, poses.fixed, k, dtype)
    ours = packed.placed(params, chosen, motion)
    ref = _three_motions(params, chosen, poses, k)
    tol = 1e-12 if dtype == torch.float64 else 2e-5  # float32: each of the three motions rounds
    for a, b in zip(ours.tensors(), ref.tensors()):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    leaves = [t for m in params for t in m.tensors()] + [poses.omega, poses.delta]
    cot = [torch.randn(t.shape, generator=g, dtype=torch.float64).to(dtype) for t in ref.tensors()]
    got = torch.autograd.grad(ours.tensors(), leaves, cot, allow_unused=True)
    want = torch.autograd.grad(ref.tensors(), leaves, cot, allow_unused=True)
    for a, b in zip(got, want):
        if a is None or b is None:
            assert a is None and b is None or float((a if a is not None else b).abs().max()) == 0.0
            continue
        torch.testing.assert_close(a, b, rtol=10 * tol, atol=10 * tol)
