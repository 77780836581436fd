"""kornia's ALIKED forward without its dense descriptor map (:func:`aliked_sparse`): the same keypoints, scores and
descriptors without the 128-channel full-size map (peak memory of one 1024 × 576 photo 1342 → 838 MiB; CPU time
the same within the noise of a loaded machine: the backbone's convolutions dominate).

kornia's ``ALIKED.extract_dense_map`` upsamples the backbone's four feature maps (32 channels each, at 1, 1/2, 1/8
and 1/32 of the image) to the image size, concatenates them (128 channels) and L2-normalises every pixel: four
full-size 128-channel passes over memory (300 MB a photo at 1024 × 576). Only two things read that map:

- the score head, whose first layer is a 1 × 1 convolution: it commutes with the bilinear upsampling (both linear,
  the upsampling's weights sum to 1), so each part is convolved at its own size to 8 channels and then upsampled;
- the descriptor head (SDDH), which reads the normalised map at a 3 × 3 patch and 16 bilinear samples per keypoint:
  here the map's value at each needed pixel is computed from the four parts (the upsampling's formula), normalised,
  then interpolated as ``grid_sample`` does (zero outside the image).

Equal to its twin, kornia's ``ALIKED.forward``, up to float32 rounding (tests/pipeline/learned/
test_aliked_sparse.py); the top-k keypoint selection makes a rounding tie able to swap a keypoint at the budget's edge.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["aliked_sparse"]

PART_SCALES = (1, 2, 8, 32)
"""Downsampling of the backbone's four feature maps (kornia's ``upsample2/8/32``; ``x1`` at full size)."""


def _upsampled_at(flat: torch.Tensor, hw: tuple[int, int], size: tuple[int, int], rows: torch.Tensor,
                  cols: torch.Tensor) -> torch.Tensor:  # fmt: skip
    """``F.interpolate(part, size, bilinear, align_corners=True)`` read at integer pixels only.

    Args:
        flat: one feature map, pixels as rows. [h * w, C]
        hw: its (h, w).
        size: (H, W) of the upsampled map.
        rows, cols: integer pixels of the upsampled map, inside it. [P] int64
    Returns:
        The upsampled map's values there. [P, C]
    """
    h, w = hw
    H, W = size

    def axis(dst: torch.Tensor, n_in: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        scale = (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
        src = dst.to(torch.float32) * scale
        i0 = src.floor().long().clamp(0, n_in - 1)
        i1 = torch.clamp(i0 + 1, max=n_in - 1)
        return i0, i1, (src - i0).unsqueeze(1)

    y0, y1, ly = axis(rows, h, H)
    x0, x1, lx = axis(cols, w, W)

    def px(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return flat.index_select(0, y * w + x)

    top = px(y0, x0) * (1 - lx) + px(y0, x1) * lx
    bottom = px(y1, x0) * (1 - lx) + px(y1, x1) * lx
    return top * (1 - ly) + bottom * ly


class _SparseMap:
    """The L2-normalised 128-channel feature map of one image, computed only at the pixels asked for.

    ``parts``: the four gated 1 × 1 projections ([32, H_p / s, W_p / s] each, s in :data:`PART_SCALES`) of the
    padded image; ``pad``: (left, top) padding; ``size``: (h, w) of the unpadded image.
    """

    def __init__(self, parts: list[torch.Tensor], pad: tuple[int, int], size: tuple[int, int]) -> None:
        self.pad, self.size = pad, size
        self.padded = tuple(parts[0].shape[-2:])
        self.hw = [tuple(p.shape[-2:]) for p in parts]
        self.flat = [p.reshape(p.shape[0], -1).t().contiguous() for p in parts]  # [h * w, 32] each
        self.channels = sum(p.shape[0] for p in parts)

    def at(self, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """The normalised features at unpadded integer pixels inside the image. [P] → [P, 128]"""
        r, c = rows + self.pad[1], cols + self.pad[0]
        w = self.padded[1]
        x1 = self.flat[0].index_select(0, r * w + c)
        ups = [_upsampled_at(f, hw, self.padded, r, c) for f, hw in zip(self.flat[1:], self.hw[1:])]  # type: ignore[arg-type]
        return F.normalize(torch.cat([x1, *ups], dim=1), p=2, dim=1)

    def bilinear(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``grid_sample`` (bilinear, ``align_corners=True``, zeros outside) at pixel positions. [P] → [P, 128]

        The four corners of every position are read at once, each distinct pixel once."""
        h, w = self.size
        x0, y0 = x.floor(), y.floor()
        xi = torch.stack([x0, x0 + 1, x0, x0 + 1])  # [4, P]
        yi = torch.stack([y0, y0, y0 + 1, y0 + 1])
        wgt = (1 - (x - xi).abs()) * (1 - (y - yi).abs())
        ok = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
        wgt = torch.where(ok, wgt, torch.zeros_like(wgt))
        lin = torch.where(ok, yi * w + xi, torch.zeros_like(xi)).long().reshape(-1)
        uniq, inverse = torch.unique(lin, return_inverse=True)
        feats = self.at(uniq // w, uniq % w).index_select(0, inverse).reshape(4, len(x), -1)
        return (feats * wgt[..., None]).sum(0)


def _layout(model: torch.nn.Module) -> torch.memory_format:
    """The memory layout of the backbone's first convolution's weights (``models.ALIKED_LAYOUT``): the image's."""
    w = next(p for p in model.parameters() if p.dim() == 4 and p.shape[-1] > 1)
    return torch.channels_last if w.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format


def _dense_parts(model: torch.nn.Module, image: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor, tuple]:
    """The backbone's four projections and the score map (unpadded, [1, 1, h, w]) of one image [1, 3, h, w]."""
    from kornia.feature.aliked.aliked import InputPadder

    padder = InputPadder(image.shape[-2], image.shape[-1], 32)
    x = padder.pad(image).contiguous(memory_format=_layout(model))
    x1 = model.block1(x)
    x2 = model.block2(model.pool2(x1))
    x3 = model.block3(model.pool4(x2))
    x4 = model.block4(model.pool4(x3))
    parts = [model.gate(conv(p)) for conv, p in zip((model.conv1, model.conv2, model.conv3, model.conv4),
                                                     (x1, x2, x3, x4))]  # fmt: skip
    head = model.score_head
    w_first = head[0].weight  # [8, 128, 1, 1], no bias
    ups = (None, model.upsample2, model.upsample8, model.upsample32)
    s = None
    for k, (p, up) in enumerate(zip(parts, ups)):
        y = F.conv2d(p, w_first[:, 32 * k : 32 * (k + 1)])
        y = y if up is None else up(y)
        s = y if s is None else s + y
    score = padder.unpad(torch.sigmoid(head[1:](s)))
    return [p[0] for p in parts], score, (padder._pad[0], padder._pad[2])


def _descriptors(model: torch.nn.Module, fmap: _SparseMap, kp_norm: torch.Tensor) -> torch.Tensor:
    """SDDH's descriptors (kornia's ``SDDH.forward`` without ``mask`` or ``conv2d``) read from ``fmap``. [N, 128]"""
    sddh = model.desc_head
    h, w = fmap.size
    wh = torch.tensor([[w - 1, h - 1]], dtype=torch.float32)
    kp_wh = (kp_norm / 2 + 0.5) * wh
    n, ps = len(kp_wh), sddh.kernel_size
    corner = (kp_wh.long() - ps / 2 + 1).long()
    cx = corner[:, 0].clamp(min=0, max=w - 1 - ps)
    cy = corner[:, 1].clamp(min=0, max=h - 1 - ps)
    d = torch.arange(ps)
    rows = (cy[:, None, None] + d[None, :, None]).expand(n, ps, ps).reshape(-1)
    cols = (cx[:, None, None] + d[None, None, :]).expand(n, ps, ps).reshape(-1)
    patch = fmap.at(rows, cols).reshape(n, ps, ps, -1).permute(0, 3, 1, 2)  # [N, C, ps, ps]
    max_offset = max(h, w) / 4.0
    offset = sddh.offset_conv(patch).clamp(-max_offset, max_offset)
    offset = offset[:, :, 0, 0].view(n, 2, sddh.n_pos).permute(0, 2, 1)
    pos = kp_wh.unsqueeze(1) + offset  # [N, n_pos, 2] pixels
    pos = (2.0 * pos / wh[None] - 1 + 1) / 2 * wh[None]  # kornia's round trip through grid_sample's [-1, 1]
    feats = fmap.bilinear(pos[..., 0].reshape(-1), pos[..., 1].reshape(-1))  # [N * n_pos, C]
    feats = feats.reshape(n, sddh.n_pos, -1).permute(0, 2, 1).unsqueeze(-1)  # [N, C, n_pos, 1]
    feats = torch.selu_(sddh.sf_conv(feats)).squeeze(-1)
    descs = torch.einsum("ncp,pcd->nd", feats, sddh.agg_weights)
    return F.normalize(descs, p=2.0, dim=1)


def aliked_sparse(model: torch.nn.Module, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """kornia's ``ALIKED.forward`` on one image without the dense descriptor map (module docstring).

    Args:
        model: kornia's ALIKED (no mask, no ``conv2d`` aggregation: the ``n16`` variants), in evaluation mode.
        image: RGB in [0, 1]. [1, 3, h, w] float32
    Returns:
        keypoints (pixels, centres at integers) [N, 2], descriptors [N, 128] (unit), scores [N].
    """
    if model.desc_head.mask or model.desc_head.conv2d:
        raise ValueError("aliked_sparse supports ALIKED without mask and conv2d aggregation (aliked-n16)")
    parts, score, pad = _dense_parts(model, image)
    h, w = image.shape[-2:]
    keypoints, scores, _ = model.dkd(score)
    fmap = _SparseMap(parts, pad, (h, w))
    desc = _descriptors(model, fmap, keypoints[0])
    wh = torch.tensor([w - 1, h - 1], dtype=torch.float32)
    return wh * (keypoints[0] + 1) / 2.0, desc, scores[0]
