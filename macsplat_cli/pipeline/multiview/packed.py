"""The joint refinement's leaves: each photo's valid Gaussians packed, and the ones each photo's step renders.

A photo's pixel map holds every pixel, but after the co-visibility init most are invalid (on the 32-photo orbit 23 %
of the pooled pixels are valid; on 4 photos ~60 %): packing the valid ones into a one-row map (``[1, 1, n]``) makes
the optimiser's step, the gradients and the gathers follow the Gaussians, not the pixels. The values, their order
(the map's row-major order, as :meth:`GaussianMaps.to_gaussians` takes them) and the arithmetic are those of the
pixel map, so the refinement computes the same numbers. The MAC loss samples maps at pixel positions: it gets the
pixel map with the packed values put back (differentiably; the invalid pixels keep their values).

A photo's step renders only the Gaussians that may fall on it (:func:`in_view`): tested once, on the registered
poses, with a margin for what the refinement moves; and each map's Gaussians are placed for it by one rigid motion
(:func:`placements`, :func:`placed`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ...gaussians import GaussianMaps, Gaussians
from ...rotations import quat_multiply, quat_to_rotmat, rotmat_to_quat

__all__ = [
    "CULL_MARGIN", "Frames", "Motion", "Packed", "centres", "conj", "frames_of", "in_view", "indices", "maps_where",
    "placed", "placements",
]  # fmt: skip

CULL_MARGIN = 0.1
"""A photo's step renders the Gaussians whose 3.5σ disc (the projection's own extent is 3σ) reaches its image widened
by this share of its long side on each side: the margin covers what the refinement moves (a free camera turns a few
tenths of a degree, a pixel or two at the refinement's resolution), so the render is the whole scene's."""


@dataclass
class Packed:
    """One photo's map as the refinement optimises it.

    Attributes:
        leaves: the valid Gaussians, a map one row wide (``valid`` None, ``cam_to_world`` the photo's). [1, 1, n, ·]
        full: the pixel map they came from (not optimised). [1, H, W, ·]
        idx: the valid pixels' row-major indices in ``full``. [n] int64
    """

    leaves: GaussianMaps
    full: GaussianMaps
    idx: torch.Tensor

    @staticmethod
    def of(m: GaussianMaps) -> Packed:
        """``m``'s valid Gaussians as leaves that require gradients (copies: ``m`` is not modified)."""
        idx = m.valid_mask()[0].reshape(-1).nonzero().squeeze(1)
        ts = [t[0].reshape(-1, *t.shape[3:])[idx][None, None].clone().requires_grad_(True) for t in m.tensors()]
        return Packed(GaussianMaps(ts[0], ts[1], ts[2], ts[3], ts[4], None, m.cam_to_world), m, idx)

    def pixel_map(self) -> GaussianMaps:
        """The pixel map with the leaves' values at the valid pixels (differentiable in the leaves). [1, H, W, ·]"""
        ts = []
        for full, leaf in zip(self.full.tensors(), self.leaves.tensors()):
            flat = full[0].reshape(-1, *full.shape[3:]).index_put((self.idx,), leaf[0, 0])
            ts.append(flat.reshape(full.shape))
        return GaussianMaps(ts[0], ts[1], ts[2], ts[3], ts[4], self.full.valid, self.full.cam_to_world)


def centres(maps: list[GaussianMaps]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each map's valid Gaussians' world centres [n, 3] and largest scale [n] (float32, as registered), in the
    order :meth:`GaussianMaps.to_gaussians` takes them."""
    out = []
    for m in maps:
        T = m.cam_to_world_or_identity(torch.float32)[0]
        valid = m.valid_mask()[0].reshape(-1)
        x = m.means[0].detach().reshape(-1, 3)[valid].float() @ T[:3, :3].T + T[:3, 3]
        out.append((x, m.log_scales[0].detach().reshape(-1, 3)[valid].float().max(-1).values.exp()))
    return out


def in_view(
    maps: list[GaussianMaps], where: list[tuple[torch.Tensor, torch.Tensor]], world_to_cam: torch.Tensor,
    K: torch.Tensor, width: int, height: int,
) -> list[torch.Tensor | None]:  # fmt: skip
    """Each map's valid Gaussians (``where``: :func:`centres`) that may be drawn in a photo (its ``world_to_cam``
    [4, 4], ``K`` [3, 3], size): the centre in front of the camera and its 3.5σ disc, widened by
    :data:`CULL_MARGIN` of the image, on the image. Per map [1, H, W] bool, or None where it has none."""
    K, V = K.float(), world_to_cam.float()
    pad = CULL_MARGIN * max(width, height)
    out: list[torch.Tensor | None] = []
    for m, (x, s) in zip(maps, where):
        X = x @ V[:3, :3].T + V[:3, 3]
        z = X[:, 2].clamp_min(1e-12)
        u, v = X[:, 0] / z, X[:, 1] / z
        r = (3.5 * K[0, 0]) * s / z * (1 + u.abs() + v.abs()) + pad
        px, py = K[0, 0] * u + K[0, 2], K[1, 1] * v + K[1, 2]
        seen = m.valid_mask().clone()
        seen[seen.clone()] = (X[:, 2] > 0) & (px + r >= 0) & (px - r <= width) & (py + r >= 0) & (py - r <= height)
        out.append(seen if bool(seen.any()) else None)
    return out


def maps_where(m: GaussianMaps, mask: torch.Tensor) -> GaussianMaps:
    """A one-view map with ``valid`` replaced by ``mask`` [1, H, W] (its world Gaussians: ``.to_gaussians()``)."""
    return GaussianMaps(m.means, m.log_scales, m.quats, m.opacity_logits, m.sh, mask, m.cam_to_world)


def indices(visible: list[torch.Tensor | bool | None]) -> list[torch.Tensor | bool | None]:
    """A photo's per-map masks (:func:`in_view` [1, 1, n], True for all, None for none) as the indices
    :func:`placed` gathers [n'] (once: they do not change)."""
    return [m.reshape(-1).nonzero().squeeze(1) if isinstance(m, torch.Tensor) else m for m in visible]


def conj(q: torch.Tensor) -> torch.Tensor:
    """The conjugate (inverse rotation) of (w, x, y, z) quaternions. [..., 4]"""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def _left(q: torch.Tensor) -> torch.Tensor:
    """The matrices of ``x ↦ q ⊗ x`` for (w, x, y, z) quaternions (:func:`~macsplat_cli.rotations.quat_multiply`'s
    product as one linear map). [C, 4] → [C, 4, 4]"""
    w, x, y, z = q.unbind(-1)
    rows = [[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


Frames = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""Each map's registered camera-to-world as :meth:`GaussianMaps.to_gaussians` applies it: rotation [C, 3, 3],
translation [C, 3] and the rotation's quaternion [C, 4], float64."""
Motion = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""One rigid motion per map: ``(A [C, 3, 3], b [C, 3], Q [C, 4, 4])``, map ``j``'s ``means ↦ means @ A_jᵀ + b_j``,
``quats ↦ quats @ Q_jᵀ``."""


def frames_of(maps: list[GaussianMaps]) -> Frames:
    """The (one-view) maps' :data:`Frames`."""
    T = torch.cat([m.cam_to_world_or_identity(torch.float64) for m in maps])
    return T[:, :3, :3], T[:, :3, 3], rotmat_to_quat(T[:, :3, :3])


def placements(
    frames: Frames, q: torch.Tensor, c: torch.Tensor, c0: torch.Tensor, fixed: int, k: int, dtype: torch.dtype
) -> Motion:
    """Each map's one rigid motion from its camera frame to where photo ``k``'s unrefined camera sees it (the joint
    refinement, :mod:`.joint`): its registered pose (``frames``, as :meth:`GaussianMaps.to_gaussians` places it),
    then its camera's update ``X ↦ Exp(ω_j)(X − c_j) + c'_j`` (the Gaussians ride with the camera), then for a camera
    ``k`` other than ``fixed`` the world placed so that the unrefined camera sees it as the refined one (``X ↦
    Exp(−ω_k)(X − c'_k) + c_k``). Composed in float64 (the three motions applied one after another in float32 differ
    at the rounding), then rounded to ``dtype``.

    Args:
        q: each camera's rotation update ``Exp(ω)`` as a quaternion. [C, 4] float64
        c: each camera's refined centre ``c'``. [C, 3] float64
        c0: each camera's registered centre. [C, 3] float64
    """
    Rm, tm, qm = frames
    R = quat_to_rotmat(q)
    A = R @ Rm
    b = ((tm - c0)[:, None] @ R.transpose(1, 2))[:, 0] + c
    Q = quat_multiply(q, qm)
    if k != fixed:
        inv = conj(q[k])
        Rk = quat_to_rotmat(inv)
        A, b, Q = Rk @ A, (b - c[k]) @ Rk.T + c0[k], quat_multiply(inv.expand_as(Q), Q)
    return A.to(dtype), b.to(dtype), _left(Q).to(dtype)


def placed(params: list[GaussianMaps], chosen: list[torch.Tensor | bool | None], motion: Motion) -> Gaussians:
    """The leaves ``chosen`` (per map the indices :func:`indices` gives, True for all, None for none) moved by
    their map's ``motion`` (:func:`placements`), concatenated in map order (differentiable w.r.t. the leaves and
    the motion): :meth:`Gaussians.cat` of the maps' parts, without its SH padding copies where every map has the
    same SH degree."""
    A, b, Q = motion
    parts: list[list[torch.Tensor]] = []
    for j, (m, sel) in enumerate(zip(params, chosen)):
        if sel is None:
            continue
        flat = [t.reshape(-1, *t.shape[3:]) for t in m.tensors()]
        if isinstance(sel, torch.Tensor):
            flat = [t.index_select(0, sel) for t in flat]
        means, log_scales, quats, opacity_logits, sh = flat
        parts.append([torch.addmm(b[j], means, A[j].T), log_scales, quats @ Q[j].T, opacity_logits, sh])
    if len({p[4].shape[1] for p in parts}) != 1:
        return Gaussians.cat([Gaussians(*p) for p in parts])
    return Gaussians(*(torch.cat(field) for field in zip(*parts)))
