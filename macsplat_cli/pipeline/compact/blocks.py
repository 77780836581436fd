"""The compaction's adaptive step: flat, uniform pixel blocks (a quadtree of 2×2 … ``max_block`` blocks) become one
Gaussian each; edges and texture keep one Gaussian per pixel."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ...gaussians import Gaussians
from ...rotations import rotmat_to_quat
from ...sh import C0
from .config import CompactConfig
from .state import NEIGHBOURS, ViewState, covariances, logit

__all__ = ["adaptive", "blocks", "depth_edges"]


def depth_edges(v: ViewState, tol: float) -> torch.Tensor:
    """Pixels on the near side of a depth step: a neighbour more than ``tol`` (relative) farther. [H, W] bool

    Only the near side: a merged block there, widened by ``coverage``, would hang in front of the background (a
    fattened silhouette in every other view). A far-side block's overhang lies behind the nearer surface, hidden
    where the photos saw it and the background's own continuation where a novel view sees past the step. Pixels
    without a Gaussian (outside the mask, or dropped by the depth fusion as a wrong layer) are no edge either:
    the block's overhang into them stays on the block's own surface.
    """
    h, w = v.size
    z = torch.where(v.valid, v.means[..., 2], torch.zeros_like(v.logits))
    zp = F.pad(z[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]  # the image border is no edge
    edge = torch.zeros(h, w, dtype=torch.bool)
    for dy, dx in NEIGHBOURS:
        zn = zp[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        edge |= (zn > 0) & (zn - z > tol * z.abs())
    return edge & v.valid


def blocks(x: torch.Tensor, s: int) -> torch.Tensor:
    """``[H, W, ...]`` → ``[H // s, W // s, s², ...]`` (the bottom/right remainder dropped)."""
    h, w = x.shape[:2]
    hb, wb = h // s, w // s
    rest = x.shape[2:]
    x = x[: hb * s, : wb * s].reshape(hb, s, wb, s, *rest).transpose(1, 2)
    return x.reshape(hb, wb, s * s, *rest)


def _mergeable(
    v: ViewState, cfg: CompactConfig, sizes: list[int]
) -> tuple[dict[int, torch.Tensor], dict[int, tuple[torch.Tensor, torch.Tensor]]]:
    """Per block size ``s``: which ``s × s`` blocks may become one Gaussian ([H // s, W // s] bool), and each block's
    points' mean [.., 3] and spread [.., 3, 3] (float64)."""
    h, w = v.size
    rgb_chw = (v.sh[..., 0, :] * C0 + 0.5).permute(2, 0, 1).double()  # [3, H, W]
    mergeable = v.alive & ~depth_edges(v, cfg.edge_depth_tol)
    ok: dict[int, torch.Tensor] = {}
    stats: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
    for s in sizes:
        if h < s or w < s:
            break
        # the cheap tests first (all pixels alive, uniform colour, children merged); the plane fit only
        # on the blocks that pass them (most textured blocks fail the colour test)
        cand = blocks(mergeable, s).all(-1)  # [hb, wb]
        # colour std per block from pooled moments (E[x²] − E[x]²: ten times faster than Tensor.std)
        m1 = F.avg_pool2d(rgb_chw, s)
        var = (F.avg_pool2d(rgb_chw * rgb_chw, s) - m1 * m1).clamp_min(0.0)
        cand &= var.sqrt().amax(0) <= cfg.color_tol
        if s > 2 and (s // 2) in ok:
            child = ok[s // 2][: 2 * cand.shape[0], : 2 * cand.shape[1]]
            cand &= child.reshape(cand.shape[0], 2, cand.shape[1], 2).all(3).all(1)
        ci = cand.nonzero(as_tuple=True)
        P = blocks(v.means, s)[ci].double()  # [M, s², 3]
        mu_c = P.mean(1)
        d = P - mu_c[:, None]
        spread_c = d.transpose(-1, -2) @ d / (s * s)  # [M, 3, 3]
        lam = torch.linalg.eigvalsh(spread_c)
        flat = lam[:, 0].clamp_min(0).sqrt() <= cfg.plane_tol * mu_c[:, 2].abs() / v.focal
        good = torch.zeros_like(cand)
        good[ci] = flat
        mu = torch.zeros(*cand.shape, 3, dtype=torch.float64)
        spread = torch.zeros(*cand.shape, 3, 3, dtype=torch.float64)
        mu[ci], spread[ci] = mu_c, spread_c
        ok[s] = good
        stats[s] = (mu, spread)
    return ok, stats


def _block_gaussians(
    v: ViewState, s: int, bi: tuple[torch.Tensor, ...], mu: torch.Tensor, spread: torch.Tensor, cfg: CompactConfig
) -> Gaussians:
    """One Gaussian per selected ``s × s`` block ``bi`` (camera frame): moment-matched mean and covariance, in-plane
    extent widened by ``coverage``, colour averaged, opacity ``1 − (1 − ō)^opacity_boost``."""
    cov = covariances(blocks(v.log_scales, s)[bi].double(), blocks(v.quats, s)[bi].double())  # [M, s², 3, 3]
    sig = spread[bi] + cov.mean(1)  # moment matching [M, 3, 3]
    lam, vec = torch.linalg.eigh(sig)
    lam = lam.clamp_min(1e-20)
    lam = torch.cat([lam[:, :1], lam[:, 1:] * cfg.coverage**2], 1)  # widen in the plane only
    opac = 1.0 - (1.0 - torch.sigmoid(blocks(v.logits, s)[bi].double()).mean(1)) ** cfg.opacity_boost
    sh = blocks(v.sh, s)[bi].mean(1)
    # local axes: (in-plane major, in-plane minor, normal) → scales in that order
    R = torch.stack([vec[:, :, 2], vec[:, :, 1], vec[:, :, 0]], 2)
    R[:, :, 2] *= torch.linalg.det(R)[:, None]
    scales = torch.stack([lam[:, 2], lam[:, 1], lam[:, 0]], 1).sqrt()
    return Gaussians(
        mu[bi].to(v.means.dtype),
        torch.log(scales).to(v.means.dtype),
        rotmat_to_quat(R).to(v.means.dtype),
        logit(opac).to(v.means.dtype),
        sh.to(v.means.dtype),
    )


def adaptive(views: list[ViewState], cfg: CompactConfig) -> tuple[str, list[Gaussians | None]]:
    """Merge flat uniform blocks, the largest first; returns each view's merged-block Gaussians (camera frame; None:
    no block merged) and marks their pixels dead (the block Gaussian replaces them)."""
    sizes = [s for s in (2, 4, 8, 16) if s <= cfg.max_block]
    out: list[Gaussians | None] = []
    for v in views:
        h, w = v.size
        ok, stats = _mergeable(v, cfg, sizes)
        taken = torch.zeros(h, w, dtype=torch.bool)
        parts = []
        for s in sorted(ok, reverse=True):
            hb, wb = ok[s].shape
            free = ~blocks(taken, s).any(-1)
            sel = ok[s] & free
            if not sel.any():
                continue
            pix = sel.repeat_interleave(s, 0).repeat_interleave(s, 1)
            taken[: hb * s, : wb * s] |= pix
            mu, spread = stats[s]
            parts.append(_block_gaussians(v, s, sel.nonzero(as_tuple=True), mu, spread, cfg))
        v.alive &= ~taken
        out.append(Gaussians.cat(parts) if parts else None)
    reason = (
        f"blocks up to {cfg.max_block}×{cfg.max_block} px with colour std ≤ {cfg.color_tol:g} and points within "
        f"{cfg.plane_tol:g} px footprints of a plane became one Gaussian each"
    )
    return reason, out
