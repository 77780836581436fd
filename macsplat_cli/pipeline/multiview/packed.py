"""The joint refinement's leaves: each photo's valid Gaussians packed, and the ones each photo's step renders.

A photo's pixel map holds every pixel, but after the co-visibility init most are invalid (on the 32-photo orbit 23 %
of the pooled pixels are valid; on 4 photos ~60 %): packing the valid ones into a one-row map (``[1, 1, n]``) makes
the optimiser's step, the gradients and the gathers follow the Gaussians, not the pixels. The values, their order
(the map's row-major order, as :meth:`GaussianMaps.to_gaussians` takes them) and the arithmetic are those of the
pixel map, so the refinement computes the same numbers. The MAC loss samples maps at pixel positions: it gets the
pixel map with the packed values put back (differentiably; the invalid pixels keep their values).

A photo's step renders only the Gaussians that may fall on it (:func:`in_view`): tested once, on the registered
poses, with a margin for what the refinement moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ...gaussians import GaussianMaps

__all__ = ["CULL_MARGIN", "Packed", "centres", "in_view", "maps_where"]

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
