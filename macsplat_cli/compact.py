"""Scene compaction: fewer Gaussians and less render work for (nearly) the same picture.

Every reconstruction starts with one Gaussian per valid pixel of each view. :func:`compact` turns the
per-view maps (:class:`~macsplat_cli.gaussians.GaussianMaps`, ``B = 1`` each, in their view's camera
frame) into a smaller flat :class:`~macsplat_cli.gaussians.Gaussians` set in the world frame, with a
:class:`CompactReport` of what each step removed and why. The steps, in the order they run (each can
be switched off in :class:`CompactConfig`):

1. **prune_opacity**: non-finite Gaussians and opacities below the renderer's ``ALPHA_MIN`` (the
   renderer culls them: provably invisible).
2. **prune_floaters**: a pixel Gaussian with fewer than ``floater_min_neighbours`` of its 8 grid
   neighbours on the same surface (relative depth within ``floater_depth_tol``): isolated depth
   outliers ("flying pixels").
3. **dedup**: a view-``k`` Gaussian that projects into an earlier view onto a valid pixel of
   consistent depth (relative tolerance ``dedup_depth_tol``) is the same surface seen twice; it is
   merged into that view's Gaussian (positions and colours averaged, opacity the larger one, the
   earlier view's scales and rotation kept, since they tile that view's pixel grid). View-``k``
   Gaussians that sample the surface ``dedup_finer_ratio`` times more finely are kept.
4. **prune_occluded**: Gaussians that no camera sees: behind an opaque Gaussian (z-buffer of the
   centres, relative tolerance ``occlusion_depth_tol``) or outside the image, in every view.
5. **prune_subpixel**: Gaussians whose largest projected standard deviation is below
   ``subpixel_px`` pixels in every view.
6. **adaptive**: per view, a quadtree over ``2×2 … max_block`` pixel blocks: a block whose pixels all
   carry a Gaussian, with a colour standard deviation below ``color_tol`` and points on a plane
   (out-of-plane deviation below ``plane_tol`` pixel footprints) becomes one Gaussian (moment-matched
   mean and covariance, in-plane extent widened by ``coverage``, colour averaged, opacity
   ``1 − (1 − ō)^opacity_boost``: it stands for several overlapping Gaussians whose alphas accumulate).
   Blocks on the near side of a depth step (a neighbour ``edge_depth_tol`` farther) are never merged.
   Edges and texture keep one Gaussian per pixel.
7. **sh**: the SH degree drops to the lowest one whose colours differ from the full degree's by less
   than ``sh_tol`` (95th percentile over the Gaussians, seen from every camera and the midpoints
   between them); with the photos given, a higher degree is kept only if it lowers the colour
   error against them by more than ``sh_tol``.
8. **budget**: at most ``budget`` Gaussians, the most important ones (opacity × largest projected area).

Everything is vectorised over pixels and blocks (no Python loop per Gaussian): a 512×352 pair
compacts in a fraction of a second on a CPU.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch
import torch.nn.functional as F

from ._json import to_jsonable
from .cameras import Camera
from .errors import InputError
from .gaussians import GaussianMaps, Gaussians
from .render._constants import ALPHA_MIN
from .rotations import quat_multiply, quat_to_rotmat, rotmat_to_quat, rotmat_to_quat_np
from .sh import C0, eval_sh, num_sh_bases

if TYPE_CHECKING:
    from .pipeline.run import Reconstruction

__all__ = ["PRESETS", "CompactConfig", "CompactReport", "CompactStep", "compact", "compact_reconstruction"]

logger = logging.getLogger(__name__)

Preset = Literal["fast", "balanced", "best"]
PRESETS: tuple[str, ...] = ("fast", "balanced", "best")
"""The named settings of :meth:`CompactConfig.preset` (``--quality``)."""


@dataclass
class CompactConfig:
    """Settings of :func:`compact`; the defaults are the ``"balanced"`` preset.

    Args:
        name: the preset these settings came from (reported only).
        prune_floaters: remove isolated pixel Gaussians.
        floater_min_neighbours: fewest of the 8 grid neighbours on the same surface to keep a Gaussian.
        floater_depth_tol: a neighbour is on the same surface within this relative depth difference.
        dedup: merge Gaussians that two views share.
        dedup_depth_tol: relative depth tolerance of the reprojection test.
        dedup_finer_ratio: a later view's Gaussian whose pixel footprint is this many times smaller than
            the earlier view's (it sees the surface in more detail) is kept, not merged.
        prune_occluded: remove Gaussians that no view sees.
        occlusion_depth_tol: relative depth margin of the z-buffer test.
        occluder_min_opacity: only Gaussians at least this opaque hide others.
        subpixel_px: remove Gaussians whose largest projected std is below this (pixels) in every view;
            0 disables the step.
        adaptive: merge flat, uniform pixel blocks.
        max_block: largest block side (2, 4, 8 or 16); blocks are 2, 4, … up to it.
        color_tol: largest colour standard deviation (per channel, colours in [0, 1]) of a merged block.
        plane_tol: largest out-of-plane standard deviation of a merged block, in pixel footprints.
        edge_depth_tol: pixels with a neighbour this much farther (relative depth: the near side of a depth step)
            are never merged.
        coverage: the merged Gaussian's in-plane standard deviations relative to the block's moment-matched
            ones (> 1 closes the seams between neighbouring blocks).
        opacity_boost: a merged Gaussian's opacity is ``1 − (1 − ō)^opacity_boost`` (ō: its pixels' mean): one
            Gaussian stands for several overlapping ones, whose alphas accumulate.
        sh: ``"auto"``: drop SH bands that do not matter (see the module docstring); ``"keep"``: keep them;
            ``"zero"``: drop only bands that are exactly zero everywhere (lossless).
        sh_tol: colour tolerance of the SH step (colours in [0, 1]).
        budget: at most this many Gaussians (the most important ones); None: no limit.
    """

    name: str = "balanced"
    prune_floaters: bool = True
    floater_min_neighbours: int = 2
    floater_depth_tol: float = 0.05
    dedup: bool = True
    dedup_depth_tol: float = 0.02
    dedup_finer_ratio: float = 1.5
    prune_occluded: bool = True
    occlusion_depth_tol: float = 0.05
    occluder_min_opacity: float = 0.5
    subpixel_px: float = 0.1
    adaptive: bool = True
    max_block: int = 8
    color_tol: float = 0.06
    plane_tol: float = 0.5
    edge_depth_tol: float = 0.15
    coverage: float = 1.7
    opacity_boost: float = 2.0
    sh: Literal["auto", "keep", "zero"] = "auto"
    sh_tol: float = 2.0 / 255.0
    budget: int | None = None

    @classmethod
    def preset(cls, name: Preset | str, *, budget: int | None = None) -> CompactConfig:
        """The settings of a named preset: ``"fast"`` (most reduction), ``"balanced"`` (the default) or
        ``"best"`` (only provably invisible Gaussians and exactly-zero SH bands are removed).

        Raises:
            InputError: an unknown preset name.
        """
        if name == "balanced":
            return cls(budget=budget)
        if name == "fast":
            return cls(
                name="fast",
                max_block=16,
                color_tol=0.08,
                plane_tol=0.5,
                edge_depth_tol=0.2,
                prune_occluded=False,
                subpixel_px=0.0,
                budget=budget,
            )  # fmt: skip  (the z-buffer and footprint tests cost more time than they save Gaussians)
        if name == "best":
            return cls(
                name="best", prune_floaters=False, dedup=False, prune_occluded=False, subpixel_px=0.0,
                adaptive=False, sh="zero", budget=budget,
            )  # fmt: skip
        raise InputError(f"unknown compaction preset {name!r}: use {', '.join(PRESETS)}")

    def validate(self) -> None:
        """Raise :class:`~macsplat_cli.errors.InputError` on a setting out of range."""
        if self.max_block not in (2, 4, 8, 16):
            raise InputError(f"max_block {self.max_block}: use 2, 4, 8 or 16")
        if self.budget is not None and self.budget < 0:
            raise InputError(f"budget {self.budget}: give a number of Gaussians ≥ 0")
        if self.sh not in ("auto", "keep", "zero"):
            raise InputError(f"sh {self.sh!r}: use auto, keep or zero")
        tolerances = ("floater_depth_tol", "edge_depth_tol", "dedup_depth_tol", "occlusion_depth_tol", "color_tol")
        for name in (*tolerances, "plane_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"{name} {v}: give a finite number ≥ 0")
        if not (math.isfinite(self.coverage) and self.coverage > 0):
            raise InputError(f"coverage {self.coverage}: give a finite number > 0")


@dataclass
class CompactStep:
    """One step of :func:`compact`: Gaussians before and after it, its time and why it removed what it did."""

    name: str
    before: int
    after: int
    seconds: float
    reason: str


@dataclass
class CompactReport:
    """What :func:`compact` did.

    Attributes:
        preset: the settings' name.
        before: Gaussians in the maps (valid pixels).
        after: Gaussians returned.
        sh_degree_before: SH degree of the maps.
        sh_degree_after: SH degree of the result.
        seconds: wall time of the whole compaction.
        steps: each step that ran, in order.
    """

    preset: str
    before: int
    after: int
    sh_degree_before: int
    sh_degree_after: int
    seconds: float
    steps: list[CompactStep] = field(default_factory=list)

    @property
    def ratio(self) -> float:
        """``before / after`` (inf for an empty result)."""
        return self.before / self.after if self.after else math.inf

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON values for the run report."""
        out = to_jsonable(self)
        out["ratio"] = to_jsonable(self.ratio)
        return out

    def summary(self) -> str:
        """One line: counts and the reduction."""
        fewer = f"{self.ratio:.1f}× fewer, {self.preset}"
        return f"{self.before} → {self.after} Gaussians ({fewer}) in {self.seconds:.2f} s"


# ------------------------------------------------------------------------------------ per-view state
@dataclass
class _View:
    """One view's pixel Gaussians in its camera frame, with the pixels still alive."""

    means: torch.Tensor  # [H, W, 3] camera frame
    log_scales: torch.Tensor  # [H, W, 3]
    quats: torch.Tensor  # [H, W, 4]
    logits: torch.Tensor  # [H, W]
    sh: torch.Tensor  # [H, W, K, 3]
    alive: torch.Tensor  # [H, W] bool
    valid: torch.Tensor  # [H, W] bool, the map's own mask (before any step)
    c2w: torch.Tensor  # [4, 4] float64
    K: torch.Tensor  # [3, 3] float64, intrinsics of the map's pixel grid
    image: torch.Tensor | None  # [H, W, 3] the photo at the map's size

    @property
    def size(self) -> tuple[int, int]:
        return int(self.means.shape[0]), int(self.means.shape[1])

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def world_means(self) -> torch.Tensor:
        """Centres in the world frame. [H, W, 3] float64"""
        return self.means.double() @ self.c2w[:3, :3].T + self.c2w[:3, 3]


def _project(points: torch.Tensor, v: _View) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points [N, 3] (float64) into view ``v``: (pixel column, pixel row, camera z, inside) [N] each."""
    w2c = torch.linalg.inv(v.c2w)
    X = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = X[:, 2]
    zs = torch.where(z > 1e-9, z, torch.ones_like(z))
    uv = (X @ v.K.T)[:, :2] / zs[:, None]
    h, w = v.size
    inside = (z > 1e-9) & torch.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0)
    inside &= uv[:, 1] < h
    col = torch.where(inside, uv[:, 0], torch.zeros_like(z)).floor().long().clamp(0, w - 1)
    row = torch.where(inside, uv[:, 1], torch.zeros_like(z)).floor().long().clamp(0, h - 1)
    return col, row, z, inside


def _covariances(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """``R S² Rᵀ``. [..., 3, 3]"""
    m = quat_to_rotmat(quats) * torch.exp(log_scales)[..., None, :]
    return m @ m.transpose(-1, -2)


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(1e-6, 1.0 - 1e-6)
    return torch.log(p) - torch.log1p(-p)


# ------------------------------------------------------------------------------------ steps
def _prune_opacity(views: list[_View]) -> str:
    logit_min = math.log(ALPHA_MIN / (1.0 - ALPHA_MIN))
    for v in views:
        finite = torch.isfinite(v.means).all(-1) & torch.isfinite(v.log_scales).all(-1)
        finite &= torch.isfinite(v.quats).all(-1) & torch.isfinite(v.logits) & torch.isfinite(v.sh).flatten(2).all(-1)
        v.alive &= finite & (v.logits >= logit_min)
    return f"non-finite, or opacity < {ALPHA_MIN:.4f} (culled by the renderer)"


_NEIGHBOURS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]


def _prune_floaters(views: list[_View], cfg: CompactConfig) -> str:
    for v in views:
        z = torch.where(v.alive, v.means[..., 2], torch.zeros_like(v.logits))
        zp = F.pad(z[None, None], (1, 1, 1, 1))[0, 0]
        h, w = v.size
        count = torch.zeros_like(z)
        for dy, dx in _NEIGHBOURS:
            zn = zp[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            count += ((zn > 0) & ((zn - z).abs() <= cfg.floater_depth_tol * z.abs())).to(z.dtype)
        v.alive &= count >= cfg.floater_min_neighbours
    return f"fewer than {cfg.floater_min_neighbours} of 8 neighbours within {cfg.floater_depth_tol:.0%} depth"


def _dedup(views: list[_View], cfg: CompactConfig) -> str:
    for k in range(1, len(views)):
        vk = views[k]
        for j in range(k):
            vj = views[j]
            idx = vk.alive.reshape(-1).nonzero().squeeze(1)
            if idx.numel() == 0:
                break
            Xw = vk.world_means().reshape(-1, 3)[idx]
            col, row, z, inside = _project(Xw, vj)
            hj, wj = vj.size
            zj = vj.means[..., 2].double()[row, col]
            ok = inside & vj.alive[row, col] & ((zj - z).abs() <= cfg.dedup_depth_tol * z.abs())
            # pixel footprints on the surface (world units per pixel): keep what samples the surface finer
            zk = vk.means[..., 2].double().reshape(-1)[idx]
            ok &= zk / vk.focal * cfg.dedup_finer_ratio >= zj / vj.focal
            src, tgt = idx[ok], (row * wj + col)[ok]
            if src.numel() == 0:
                continue
            n = hj * wj
            count = torch.zeros(n, dtype=torch.float64).index_add_(0, tgt, torch.ones_like(tgt, dtype=torch.float64))
            w2c = torch.linalg.inv(vj.c2w)
            Xj = Xw[ok] @ w2c[:3, :3].T + w2c[:3, 3]  # in view j's frame
            sum_means = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, tgt, Xj)
            kk = vk.sh.shape[-2]
            sh_src = vk.sh.reshape(-1, kk, 3)[src].double()
            kj = vj.sh.shape[-2]
            if kk != kj:
                kmax = max(kk, kj)
                sh_src = F.pad(sh_src, (0, 0, 0, kmax - kk))
                if kj < kmax:
                    vj.sh = F.pad(vj.sh, (0, 0, 0, kmax - kj))
                    kj = kmax
            sum_sh = torch.zeros(n, kj, 3, dtype=torch.float64).index_add_(0, tgt, sh_src)
            max_logit = torch.full((n,), -math.inf, dtype=vk.logits.dtype)
            max_logit.scatter_reduce_(0, tgt, vk.logits.reshape(-1)[src], "amax")
            hit = count > 0
            c = count[hit][:, None]
            flat_means = vj.means.reshape(-1, 3)
            flat_means[hit] = (0.5 * flat_means[hit].double() + 0.5 * sum_means[hit] / c).to(flat_means.dtype)
            flat_sh = vj.sh.reshape(-1, kj, 3)
            flat_sh[hit] = (0.5 * flat_sh[hit].double() + 0.5 * sum_sh[hit] / c[..., None]).to(flat_sh.dtype)
            flat_logits = vj.logits.reshape(-1)
            flat_logits[hit] = torch.maximum(flat_logits[hit], max_logit[hit])
            alive = vk.alive.reshape(-1)
            alive[src] = False
    return (
        f"surface seen by an earlier view: reprojects onto a valid pixel within {cfg.dedup_depth_tol:.0%} depth "
        "(merged into it: positions and colours averaged, opacity the larger)"
    )


def _prune_occluded(views: list[_View], cfg: CompactConfig) -> str:
    worlds = [v.world_means().reshape(-1, 3) for v in views]
    seen = [torch.zeros(v.size[0] * v.size[1], dtype=torch.bool) for v in views]
    for c in views:
        h, w = c.size
        zbuf = torch.full((h * w,), math.inf, dtype=torch.float64)
        projected = []
        for v, X in zip(views, worlds):
            col, row, z, inside = _project(X, c)
            projected.append((row * w + col, z, inside))
            occ = inside & v.alive.reshape(-1) & (torch.sigmoid(v.logits.reshape(-1)) >= cfg.occluder_min_opacity)
            zbuf.scatter_reduce_(0, (row * w + col)[occ], z[occ], "amin")
        # a pixel hides what lies behind only if its 3×3 neighbourhood is covered too (the farthest of the
        # nearest depths): a lone occluder centre covers part of its pixel, and leaves no hole behind
        zbuf = F.max_pool2d(zbuf.reshape(1, 1, h, w), 3, stride=1, padding=1).reshape(-1)
        for s, (pix, z, inside) in zip(seen, projected):
            s |= inside & (z <= zbuf[pix] * (1.0 + cfg.occlusion_depth_tol))
    for v, s in zip(views, seen):
        v.alive &= s.reshape(v.size)
    return f"hidden in every view (behind a Gaussian of opacity ≥ {cfg.occluder_min_opacity:g}, or off-image)"


def _prune_subpixel(views: list[_View], cfg: CompactConfig) -> str:
    worlds = [v.world_means().reshape(-1, 3) for v in views]
    for v, X in zip(views, worlds):
        sigma = torch.exp(v.log_scales.double().amax(-1)).reshape(-1)
        best = torch.zeros_like(sigma)
        for c in views:
            _, _, z, inside = _project(X, c)
            px = torch.where(inside, sigma * c.focal / z.clamp_min(1e-12), torch.zeros_like(sigma))
            best = torch.maximum(best, px)
        v.alive &= (best >= cfg.subpixel_px).reshape(v.size)
    return f"largest projected std below {cfg.subpixel_px:g} px in every view"


def _depth_edges(v: _View, tol: float) -> torch.Tensor:
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
    for dy, dx in _NEIGHBOURS:
        zn = zp[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        edge |= (zn > 0) & (zn - z > tol * z.abs())
    return edge & v.valid


def _blocks(x: torch.Tensor, s: int) -> torch.Tensor:
    """``[H, W, ...]`` → ``[H // s, W // s, s², ...]`` (the bottom/right remainder dropped)."""
    h, w = x.shape[:2]
    hb, wb = h // s, w // s
    rest = x.shape[2:]
    x = x[: hb * s, : wb * s].reshape(hb, s, wb, s, *rest).transpose(1, 2)
    return x.reshape(hb, wb, s * s, *rest)


def _adaptive(views: list[_View], cfg: CompactConfig) -> tuple[str, list[Gaussians]]:
    """Merge flat uniform blocks; returns each view's merged-block Gaussians (camera frame) and marks their
    pixels dead (the block Gaussian replaces them)."""
    sizes = [s for s in (2, 4, 8, 16) if s <= cfg.max_block]
    out = []
    for v in views:
        h, w = v.size
        rgb_chw = (v.sh[..., 0, :] * C0 + 0.5).permute(2, 0, 1).double()  # [3, H, W]
        mergeable = v.alive & ~_depth_edges(v, cfg.edge_depth_tol)
        ok: dict[int, torch.Tensor] = {}
        stats: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        for s in sizes:
            if h < s or w < s:
                break
            # the cheap tests first (all pixels alive, uniform colour, children merged); the plane fit only
            # on the blocks that pass them (most textured blocks fail the colour test)
            cand = _blocks(mergeable, s).all(-1)  # [hb, wb]
            # colour std per block from pooled moments (E[x²] − E[x]²: ten times faster than Tensor.std)
            m1 = F.avg_pool2d(rgb_chw, s)
            var = (F.avg_pool2d(rgb_chw * rgb_chw, s) - m1 * m1).clamp_min(0.0)
            cand &= var.sqrt().amax(0) <= cfg.color_tol
            if s > 2 and (s // 2) in ok:
                child = ok[s // 2][: 2 * cand.shape[0], : 2 * cand.shape[1]]
                cand &= child.reshape(cand.shape[0], 2, cand.shape[1], 2).all(3).all(1)
            ci = cand.nonzero(as_tuple=True)
            P = _blocks(v.means, s)[ci].double()  # [M, s², 3]
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
        taken = torch.zeros(h, w, dtype=torch.bool)
        parts = []
        for s in sorted(ok, reverse=True):
            hb, wb = ok[s].shape
            free = ~_blocks(taken, s).any(-1)
            sel = ok[s] & free
            if not sel.any():
                continue
            pix = sel.repeat_interleave(s, 0).repeat_interleave(s, 1)
            taken[: hb * s, : wb * s] |= pix
            mu, spread = stats[s]
            bi = sel.nonzero(as_tuple=True)
            cov = _covariances(_blocks(v.log_scales, s)[bi].double(), _blocks(v.quats, s)[bi].double())  # [M, s², 3, 3]
            sig = spread[bi] + cov.mean(1)  # moment matching [M, 3, 3]
            lam, vec = torch.linalg.eigh(sig)
            lam = lam.clamp_min(1e-20)
            lam = torch.cat([lam[:, :1], lam[:, 1:] * cfg.coverage**2], 1)  # widen in the plane only
            opac = 1.0 - (1.0 - torch.sigmoid(_blocks(v.logits, s)[bi].double()).mean(1)) ** cfg.opacity_boost
            sh = _blocks(v.sh, s)[bi].mean(1)
            # local axes: (in-plane major, in-plane minor, normal) → scales in that order
            R = torch.stack([vec[:, :, 2], vec[:, :, 1], vec[:, :, 0]], 2)
            R[:, :, 2] *= torch.linalg.det(R)[:, None]
            scales = torch.stack([lam[:, 2], lam[:, 1], lam[:, 0]], 1).sqrt()
            parts.append(
                Gaussians(
                    mu[bi].to(v.means.dtype),
                    torch.log(scales).to(v.means.dtype),
                    rotmat_to_quat(R).to(v.means.dtype),
                    _logit(opac).to(v.means.dtype),
                    sh.to(v.means.dtype),
                )
            )
        v.alive &= ~taken
        out.append(Gaussians.cat(parts) if parts else None)
    reason = (
        f"blocks up to {cfg.max_block}×{cfg.max_block} px with colour std ≤ {cfg.color_tol:g} and points within "
        f"{cfg.plane_tol:g} px footprints of a plane became one Gaussian each"
    )
    return reason, out  # type: ignore[return-value]


def _to_world(g: Gaussians, c2w: torch.Tensor) -> Gaussians:
    """Camera-frame Gaussians → world, as :meth:`GaussianMaps.to_gaussians` does it."""
    T = c2w.to(g.dtype)
    q = torch.as_tensor(rotmat_to_quat_np(c2w[:3, :3].numpy()), dtype=g.dtype)
    return Gaussians(
        g.means @ T[:3, :3].T + T[:3, 3], g.log_scales, quat_multiply(q.expand(len(g), 4), g.quats),
        g.opacity_logits, g.sh,
    )  # fmt: skip


def _sh_degree(g: Gaussians, cams: list[_View], cfg: CompactConfig) -> tuple[int, str]:
    """The SH degree to keep, and why, from the view dependence of ``g``'s colours."""
    full = g.sh_degree
    if full == 0:
        return 0, "degree 0 already"
    if len(g) == 0:
        return 0, "no Gaussians"
    if cfg.sh == "keep":
        return full, "kept (sh='keep')"
    if cfg.sh == "zero":
        nonzero = [d for d in range(1, full + 1) if g.sh[:, num_sh_bases(d - 1) : num_sh_bases(d)].abs().amax() > 0]
        deg = max(nonzero, default=0)
        return deg, f"bands above {deg} are exactly zero" if deg < full else "every band is used"
    centres = [c.c2w[:3, 3].to(g.dtype) for c in cams]
    eyes = centres + [0.5 * (a + b) for i, a in enumerate(centres) for b in centres[i + 1 :]]
    sh = g.sh
    if len(g) > 200_000:  # a deterministic subsample is enough for a percentile
        sh = sh[:: len(g) // 200_000 + 1]
        means = g.means[:: len(g) // 200_000 + 1]
    else:
        means = g.means
    colors = {d: [] for d in range(full + 1)}
    for e in eyes:
        dirs = F.normalize(means - e, dim=-1)
        for d in range(full + 1):
            colors[d].append(eval_sh(sh[:, : num_sh_bases(d)], dirs).clamp_min(0))
    ref = torch.cat(colors[full])
    for d in range(full):
        diff = (torch.cat(colors[d]) - ref).abs().amax(-1)
        p95 = float(torch.quantile(diff.float(), 0.95)) if diff.numel() else 0.0
        if p95 <= cfg.sh_tol:
            return d, f"degree {d} differs by ≤ {p95:.4f} (95th pct) from degree {full} across the views"
    return full, f"the view-dependent colour exceeds {cfg.sh_tol:.4f} below degree {full}"


def _sh_photo_check(views: list[_View], full: int, deg: int, cfg: CompactConfig) -> tuple[int, str] | None:
    """With photos: raise ``deg`` while a higher degree lowers the mean colour error at the pixels by > sh_tol."""
    errs = []
    for d in range(full + 1):
        total, n = 0.0, 0
        for v in views:
            if v.image is None:
                return None
            sel = v.alive.reshape(-1)
            if not sel.any():
                continue
            X = v.world_means().reshape(-1, 3)[sel].to(v.sh.dtype)
            dirs = F.normalize(X - v.c2w[:3, 3].to(X.dtype), dim=-1)
            c = eval_sh(v.sh.reshape(-1, v.sh.shape[-2], 3)[sel][:, : num_sh_bases(d)], dirs).clamp(0, 1)
            total += float((c - v.image.reshape(-1, 3)[sel]).abs().mean(-1).sum())
            n += int(sel.sum())
        errs.append(total / max(n, 1))
    best = deg
    for d in range(deg + 1, full + 1):
        if errs[best] - errs[d] > cfg.sh_tol:
            best = d
    if best == deg:
        return None
    return best, f"degree {best} lowers the colour error at the photos' pixels from {errs[deg]:.4f} to {errs[best]:.4f}"


def _importance(g: Gaussians, cams: list[_View]) -> torch.Tensor:
    """Opacity × the largest projected area over the views (px²). [N]"""
    s = torch.sort(g.log_scales.double(), dim=-1, descending=True).values
    area = math.pi * torch.exp(s[:, 0] + s[:, 1])
    best = torch.zeros(len(g), dtype=torch.float64)
    for c in cams:
        _, _, z, inside = _project(g.means.double(), c)
        px = torch.where(inside, area * (c.focal / z.clamp_min(1e-12)) ** 2, torch.zeros_like(area))
        best = torch.maximum(best, px)
    return torch.sigmoid(g.opacity_logits.double()) * best


# ------------------------------------------------------------------------------------ entry points
def _views(maps: Sequence[GaussianMaps], cameras: Sequence[Camera], images: Sequence[np.ndarray] | None) -> list[_View]:
    if len(maps) != len(cameras):
        raise InputError(f"compact() got {len(maps)} maps and {len(cameras)} cameras")
    if images is not None and len(images) != len(maps):
        raise InputError(f"compact() got {len(maps)} maps and {len(images)} images")
    out = []
    for k, (m, cam) in enumerate(zip(maps, cameras)):
        if m.batch != 1:
            raise InputError(f"compact() takes one map per view (B = 1), got B = {m.batch} for view {k}")
        h, w = m.size
        c2w = torch.tensor(np.array(cam.cam_to_world), dtype=torch.float64)
        if m.cam_to_world is not None:
            mc = m.cam_to_world[0].double().cpu()
            if float((mc - c2w).abs().max()) > 1e-5:
                raise InputError(f"view {k}: the map's cam_to_world differs from the camera's pose")
            c2w = mc
        K = torch.tensor(np.array(cam.rescaled(w, h).K), dtype=torch.float64)
        img = None
        if images is not None:
            a = np.asarray(images[k], dtype=np.float32)
            if a.shape[:2] != (h, w):
                import cv2

                a = cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)
            img = torch.from_numpy(np.ascontiguousarray(a)).to(m.dtype)
        p = [t[0].contiguous().clone() for t in m.tensors()]  # a copy (the steps write into it through views)
        valid = m.valid_mask()[0].clone()
        out.append(_View(*p, valid.clone(), valid, c2w, K, img))
    return out


def compact(
    maps: Sequence[GaussianMaps],
    cameras: Sequence[Camera],
    config: CompactConfig | None = None,
    *,
    images: Sequence[np.ndarray] | None = None,
) -> tuple[Gaussians, CompactReport]:
    """A smaller set of Gaussians that renders (nearly) like the maps' full set.

    Args:
        maps: each view's pixel Gaussians (``B = 1``, in the view's camera frame, ``cam_to_world`` set or None);
            not modified. They may be smaller than the cameras' images (refined maps are pooled).
        cameras: each view's camera (intrinsics and pose; any resolution: rescaled to its map's size). The
            maps' ``cam_to_world`` must agree with the poses.
        config: the settings (default: the ``"balanced"`` preset).
        images: each view's photo in [0, 1] [H, W, 3] (any size; resized to its map), for the SH step only.

    Returns:
        ``(gaussians, report)``: the compacted Gaussians in the world frame (float32 on the CPU, as the maps)
        and what each step did.

    Raises:
        InputError: mismatched inputs or settings out of range.
    """
    cfg = config or CompactConfig()
    cfg.validate()
    t_start = time.perf_counter()
    devices = {m.device for m in maps}
    device = devices.pop() if len(devices) == 1 else torch.device("cpu")
    maps = [m.to(device="cpu") for m in maps]
    views = _views(maps, cameras, images)
    before = sum(int(v.alive.sum()) for v in views)
    sh_before = max((m.sh_degree for m in maps), default=0)
    steps: list[CompactStep] = []

    def count() -> int:
        return sum(int(v.alive.sum()) for v in views)

    def run(name: str, fn: Any) -> Any:
        n0, t0 = count(), time.perf_counter()
        result = fn()
        reason = result if isinstance(result, str) else result[0]
        steps.append(CompactStep(name, n0, count(), time.perf_counter() - t0, reason))
        return result

    with torch.no_grad():
        run("prune_opacity", lambda: _prune_opacity(views))
        if cfg.prune_floaters:
            run("prune_floaters", lambda: _prune_floaters(views, cfg))
        if cfg.dedup and len(views) > 1:
            run("dedup", lambda: _dedup(views, cfg))
        if cfg.prune_occluded:
            run("prune_occluded", lambda: _prune_occluded(views, cfg))
        if cfg.subpixel_px > 0:
            run("prune_subpixel", lambda: _prune_subpixel(views, cfg))
        merged: list[Gaussians | None] = [None] * len(views)
        if cfg.adaptive:
            n0, t0 = count(), time.perf_counter()
            reason, merged = _adaptive(views, cfg)
            n1 = count() + sum(len(g) for g in merged if g is not None)
            steps.append(CompactStep("adaptive", n0, n1, time.perf_counter() - t0, reason))
        parts = []
        for v, extra in zip(views, merged):
            sel = v.alive.reshape(-1)
            k = v.sh.shape[-2]
            g = Gaussians(
                v.means.reshape(-1, 3)[sel], v.log_scales.reshape(-1, 3)[sel], v.quats.reshape(-1, 4)[sel],
                v.logits.reshape(-1)[sel], v.sh.reshape(-1, k, 3)[sel],
            )  # fmt: skip
            if extra is not None:
                g = Gaussians.cat([g, extra])
            parts.append(_to_world(g, v.c2w))
        out = Gaussians.cat(parts) if parts else Gaussians.empty()
        t0 = time.perf_counter()
        deg, reason = _sh_degree(out, views, cfg)
        if cfg.sh == "auto" and images is not None and deg < out.sh_degree:
            raised = _sh_photo_check(views, out.sh_degree, deg, cfg)
            if raised is not None:
                deg, reason = raised
        if out.sh_degree > 0:
            steps.append(CompactStep("sh", len(out), len(out), time.perf_counter() - t0, reason))
            out = dataclasses.replace(out, sh=out.sh[:, : num_sh_bases(deg)].contiguous())
        if cfg.budget is not None and len(out) > cfg.budget:
            t0 = time.perf_counter()
            n0 = len(out)
            keep = torch.topk(_importance(out, views), cfg.budget).indices.sort().values
            out = out[keep]
            why = "least important (opacity × largest projected area)"
            steps.append(CompactStep("budget", n0, len(out), time.perf_counter() - t0, why))
    out = out.to(device)
    report = CompactReport(cfg.name, before, len(out), sh_before, out.sh_degree, time.perf_counter() - t_start, steps)
    logger.debug("compaction: %s", report.summary())
    return out, report


def compact_reconstruction(rec: Reconstruction, config: CompactConfig | None = None) -> tuple[Gaussians, CompactReport]:
    """:func:`compact` on a finished (possibly refined) reconstruction: its maps, working-size cameras and photos."""
    cams = list(rec.cameras(original_size=False))
    return compact(rec.maps, cams, config, images=[v.image for v in rec.views])
