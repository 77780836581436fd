"""The training objective: ``L = L_photo + λ_MAC · L_MAC`` on a batch of pairs.

* ``L_photo`` (per target view, averaged): ``MSE + λ_lpips · LPIPS`` with LPIPS weights
  (``--lpips-weights``, Splatt3R's 0.25), else ``MSE + λ_ssim · (1 − SSIM)`` (D-SSIM stands in for the
  perceptual term when no VGG weights are given; the trainer logs which). Targets are rendered from the
  predicted Gaussians of both context views with the differentiable rasterizer (gsplat on CUDA when
  installed), from their ground-truth cameras re-expressed in context 0's frame (metric, as Splatt3R).
  With a visibility mask (Splatt3R's loss mask, from ground-truth depth) both images are masked first, and
  the means run over the whole images (``photo_reduction="image"``) or over the mask's pixels
  (``"mask"``, the MAC-Splat release's: ``Σ err² / (3 · mask pixels)``, and LPIPS's per-pixel map
  averaged over the mask; D-SSIM's map likewise), over all the sample's targets at once.
* ``L_MAC`` (:func:`macsplat_cli.mac.mac_loss`, λp = 1, λs = 0.02, λa = 0.1, weight 0.25): matched
  Gaussians of the two views pulled together in world space (the ground-truth frame of context 0). Matches
  come from the fused descriptors through the shared filtered matcher (reciprocal nearest neighbours on a
  ``match_stride`` grid, gated by ``c0·c1 > τ``), at most ``max_matches`` of them (a random subset).

**How the fusion module learns.** Reciprocal matching is discrete, so neither term would reach the fused
descriptors through the match pixels. Each match's MAC weight is therefore ``w = c0·c1·p``, with ``p`` the
dual-softmax probability of that match under the fused descriptors (temperature ``match_temperature``).
MAC normalises by ``Σ w``, so lowering every weight gains nothing: the gradient moves weight from matches
whose Gaussians disagree to those that agree, which sharpens the descriptors on geometrically consistent
correspondences. ``p`` is detached when ``descriptor_gradient=False``.

The loss is the mean of per-sample losses, so ``N`` processes with local batch ``b`` (DDP averages their
gradients) give the gradients of one process with batch ``N·b``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..cameras import Camera
from ..datasets.coverage import visibility_mask
from ..errors import InputError
from ..gaussians import GaussianMaps
from ..lpips import LPIPS
from ..mac import MACConfig, mac_loss
from ..metrics import ssim_map
from ..neural.predictor import PairPrediction
from ..pipeline.matching import MatchConfig, match_features, seeded_reciprocal_neighbours
from ..pipeline.neural.geometry import sample_descriptors
from ..pipeline.types import Features
from ..render import render

__all__ = ["LossConfig", "LossTerms", "loss_masks", "render_targets", "sample_matches", "training_loss"]


@dataclass
class LossConfig:
    """Weights of the objective (module docstring).

    Args:
        lpips_weight: λ of LPIPS (used when an LPIPS model is given).
        ssim_weight: λ of D-SSIM (used without LPIPS).
        mac_weight: λ_MAC; 0 turns MAC off (the "w/o MAC" ablation).
        mac: the MAC term's own weights (λp, λs, λa) and Huber thresholds.
        match_stride: descriptor grid step for the matches.
        conf_threshold: τ of the confidence gate on ``c0·c1``.
        match_temperature: temperature of the dual softmax giving each match's probability.
        descriptor_gradient: let the MAC weights' gradient reach the fused descriptors.
        mac_weighting: ``"c0c1p"`` (default: w = c0·c1·p, the dual-softmax probability p gives the fusion module
            its gradient) or ``"c0c1"`` (the paper's plain w = c0·c1: the fusion learns nothing from MAC).
        conf_floor: the weights use ``conf_floor + c`` for each confidence ``c = exp(x)`` (MASt3R's and the
            release's ``1 + exp(x)``: 1; macsplat: 0). The gate always tests ``c0·c1 > τ`` without it.
        max_matches: a random subset of at most this many matches per sample (None: all; the release: 4096).
        photo_reduction: ``"image"`` (means over the whole masked images) or ``"mask"`` (over the mask's
            pixels; module docstring).
        matcher: ``"grid"`` (mutual nearest neighbours on the ``match_stride`` grid) or ``"seeded"`` (reciprocal
            nearest neighbours over all pixels from a ``seed_stride`` grid of seeds, ≤ ``seed_iters`` rounds: the
            MAC-Splat release's; no match probability, so ``mac_weighting="c0c1"`` only).
        seed_stride: step of the seed grid of ``"seeded"``.
        seed_iters: most rounds of ``"seeded"``'s walks.
        near_plane: the target renders' near plane, camera z (the rasterizer's 0.01; the release: 0.1).
        geometry_weight: weight of a point-map regression term (:func:`point_regression`) for a backbone
            trained from scratch (``--init random``), whose random point maps give the head nothing to render.
        background: colour behind the Gaussians.
    """

    lpips_weight: float = 0.25
    ssim_weight: float = 0.2
    mac_weight: float = 0.25
    mac: MACConfig = field(default_factory=MACConfig)
    match_stride: int = 4
    conf_threshold: float = 1.0
    match_temperature: float = 0.1
    descriptor_gradient: bool = True
    mac_weighting: str = "c0c1p"
    conf_floor: float = 0.0
    max_matches: int | None = None
    photo_reduction: str = "image"
    matcher: str = "grid"
    seed_stride: int = 8
    seed_iters: int = 10
    near_plane: float = 0.01
    geometry_weight: float = 0.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.mac_weighting not in ("c0c1p", "c0c1"):
            raise InputError(f"--mac-weighting {self.mac_weighting!r}: use c0c1p or c0c1")
        if self.matcher not in ("grid", "seeded"):
            raise InputError(f"matcher {self.matcher!r}: use grid or seeded")
        if self.matcher == "seeded" and self.mac_weighting != "c0c1":
            raise InputError("the seeded matcher (--recipe released-code) gives no match probability p: use "
                             "--mac-weighting c0c1")  # fmt: skip
        if self.seed_stride < 1 or self.seed_iters < 1:
            raise InputError(f"seed_stride {self.seed_stride} and seed_iters {self.seed_iters} must be ≥ 1")
        if self.photo_reduction not in ("image", "mask"):
            raise InputError(f"photometric reduction {self.photo_reduction!r}: use image or mask")
        if not (self.conf_floor >= 0 and math.isfinite(self.conf_floor)):
            raise InputError(f"conf_floor {self.conf_floor}: give a finite number ≥ 0")
        if self.max_matches is not None and (int(self.max_matches) != self.max_matches or self.max_matches < 1):
            raise InputError(f"max_matches {self.max_matches!r}: give a positive integer or None")


@dataclass
class LossTerms:
    """The loss and its parts (floats, averaged over the batch)."""

    loss: torch.Tensor
    photo: float
    mse: float
    perceptual: float
    mac: float
    matches: float


def render_targets(
    maps: tuple[GaussianMaps, GaussianMaps], b: int, target_K: torch.Tensor, target_c2w: torch.Tensor,
    context_c2w: torch.Tensor, size: tuple[int, int], background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    near: float = 0.01,
) -> torch.Tensor:  # fmt: skip
    """Sample ``b``'s Gaussians (both views, context-0 frame) rendered into its targets. [T, 3, H, W]

    Args:
        maps: the predictor's Gaussian maps of view 0 and view 1. [B, H, W, ·] each
        b: the sample.
        target_K: the targets' intrinsics. [T, 3, 3]
        target_c2w: the targets' camera-to-world (data set frame). [T, 4, 4]
        context_c2w: context 0's camera-to-world (data set frame). [4, 4]
        size: (H, W) of the targets.
        near: the renders' near plane (camera z).
    """
    gaussians = GaussianMaps.cat([maps[0].view(b), maps[1].view(b)]).to_gaussians()
    dt, dev = gaussians.dtype, gaussians.device
    c2w0 = context_c2w.to(device=dev, dtype=torch.float64)
    out = []
    for K, c2w in zip(target_K, target_c2w):
        viewmat = torch.linalg.inv(c2w.to(device=dev, dtype=torch.float64)) @ c2w0  # context 0 → target
        rgb = render(
            gaussians, viewmat.to(dt), K.to(device=dev, dtype=dt), size[1], size[0], background=background, near=near
        ).rgb
        out.append(rgb.permute(2, 0, 1))
    return torch.stack(out)


def sample_matches(
    desc: torch.Tensor, desc_conf: torch.Tensor, config: LossConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Filtered matches between the two views of one sample, with a differentiable weight each.

    ``matcher="grid"``: mutual nearest neighbours among the pixels of a ``match_stride`` grid in both views;
    ``"seeded"``: reciprocal nearest neighbours over every pixel, walked to from a ``seed_stride`` grid of view 0
    (:func:`~macsplat_cli.pipeline.matching.seeded_reciprocal_neighbours`, the MAC-Splat release's). Then the gate
    ``c0·c1 > τ`` and, with ``max_matches``, a random subset (torch's global generator: a resumed run draws the same).

    Args:
        desc: the (fused) descriptors of both views. [2, H, W, D]
        desc_conf: their confidences (≥ 0). [2, H, W]

    Returns:
        ``xy0 [M, 2]``, ``xy1 [M, 2]`` (pixel centres at +0.5) and ``w [M]`` = ``c0·c1·p`` (module docstring), or
        ``c0·c1`` with ``mac_weighting="c0c1"`` (each ``c`` plus ``conf_floor``).
    """
    h, w = desc.shape[1:3]
    if config.matcher == "seeded":
        flat = torch.nn.functional.normalize(desc.reshape(2, h * w, -1).float(), dim=-1)  # [2, H·W, D]
        conf = desc_conf.reshape(2, h * w).float()
        rows, cols = torch.meshgrid(torch.arange(0, h, config.seed_stride), torch.arange(0, w, config.seed_stride),
                                    indexing="ij")  # fmt: skip
        i0, i1 = seeded_reciprocal_neighbours(flat[0].detach(), flat[1].detach(), (rows * w + cols).reshape(-1),
                                              max_iters=config.seed_iters)  # fmt: skip
        gate = conf[0, i0].detach() * conf[1, i1].detach() > config.conf_threshold
        i0, i1 = i0[gate], i1[gate]
        pix = torch.arange(h * w, device=desc.device)
    else:
        idx, grid = sample_descriptors(
            desc_conf[0].detach().float().cpu().numpy(), sampling="grid", stride=config.match_stride
        )
        pix = torch.from_numpy(idx).to(desc.device)
        uv = np.stack([idx % w + 0.5, idx // w + 0.5], 1).astype(np.float64)
        flat = torch.nn.functional.normalize(desc.reshape(2, h * w, -1)[:, pix].float(), dim=-1)  # [2, N, D]
        conf = desc_conf.reshape(2, h * w)[:, pix].float()  # [2, N]
        feats = [
            Features(uv, flat[k].detach().cpu().numpy(), conf[k].detach().cpu().numpy(), grid=grid) for k in (0, 1)
        ]
        m = match_features(
            feats[0], feats[1], MatchConfig(conf_threshold=config.conf_threshold, ratio_confidence=False)
        )
        i0, i1 = torch.from_numpy(m.idx0).to(desc.device), torch.from_numpy(m.idx1).to(desc.device)
    if config.max_matches is not None and len(i0) > config.max_matches:
        keep = torch.randperm(len(i0))[: config.max_matches].sort().values.to(desc.device)
        i0, i1 = i0[keep], i1[keep]
    weight = (config.conf_floor + conf[0, i0].detach()) * (config.conf_floor + conf[1, i1].detach())
    if config.mac_weighting == "c0c1p":  # the grid matcher only (LossConfig refuses it with "seeded")
        sim = flat[0] @ flat[1].T / config.match_temperature  # [N, N]
        p = (sim.softmax(0) * sim.softmax(1))[i0, i1]  # dual softmax of each match
        weight = weight * (p if config.descriptor_gradient else p.detach())
    p0, p1 = pix[i0].cpu(), pix[i1].cpu()
    xy0 = torch.stack([p0 % w + 0.5, p0 // w + 0.5], 1).float()
    xy1 = torch.stack([p1 % w + 0.5, p1 // w + 0.5], 1).float()
    return xy0, xy1, weight


def point_regression(
    pts3d: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor
) -> torch.Tensor | None:
    """Mean L1 between predicted and ground-truth point maps of both views in view 0's frame, over pixels with
    depth, divided by the mean ground-truth depth; None without depth.

    Args:
        pts3d: predicted point maps. [2, H, W, 3]
        depth: ground-truth depth (0 = none). [2, H, W]
        K: intrinsics. [2, 3, 3]
        c2w: camera-to-world. [2, 4, 4]
    """
    valid = depth > 0
    if not valid.any():
        return None
    h, w = depth.shape[1:]
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5, indexing="ij"
    )
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1)  # [H, W, 3]
    to0 = torch.linalg.inv(c2w[0].double())
    gts = []
    for k in (0, 1):
        cam = pix @ torch.linalg.inv(K[k].double()).T * depth[k].double()[..., None]  # camera k
        T = to0 @ c2w[k].double()
        gts.append(cam @ T[:3, :3].T + T[:3, 3])
    gt = torch.stack(gts).to(pts3d)
    scale = depth[valid].double().mean().clamp_min(1e-6).item()
    return (pts3d - gt).abs().sum(-1)[valid.to(pts3d.device)].mean() / scale


def loss_masks(batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
    """Splatt3R's visibility ("loss") mask of every target (pixels with a depth that a context view sees at
    that depth), from the batch's ground-truth depth; None when a target has no depth at all. [B, T, H, W] bool

    Without it, Gaussians grow to cover what the context views never saw (Splatt3R's "w/o masking" ablation
    diverged).
    """
    tgt_depth, ctx_depth = batch["target_depth"].numpy(), batch["context_depth"].numpy()
    n, t, h, w = tgt_depth.shape
    if not all((tgt_depth[b, k] > 0).any() for b in range(n) for k in range(t)):
        return None
    masks = np.zeros((n, t, h, w), bool)
    for b in range(n):
        ctx = [
            Camera(f"c{k}", w, h, batch["context_K"][b, k].numpy(), batch["context_c2w"][b, k].numpy()) for k in (0, 1)
        ]
        for k in range(t):
            cam = Camera("t", w, h, batch["target_K"][b, k].numpy(), batch["target_c2w"][b, k].numpy())
            masks[b, k] = visibility_mask(tgt_depth[b, k], cam, list(ctx_depth[b]), ctx)
    return torch.from_numpy(masks)


def _photometric(
    rgb: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None, config: LossConfig, lpips: LPIPS | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(MSE, LPIPS or 1 − SSIM)`` of one sample's rendered targets (module docstring).

    Args:
        rgb: the renders. [T, 3, H, W]
        gt: the targets. [T, 3, H, W]
        mask: the targets' visibility masks (None: none). [T, H, W]
    """
    t = rgb.shape[0]
    if mask is None:
        m = None
    else:
        m = mask.to(device=rgb.device, dtype=rgb.dtype)[:, None]
        rgb, gt = rgb * m, gt * m
    if m is not None and config.photo_reduction == "mask":
        px = m.sum().clamp_min(1.0)
        mse = ((rgb - gt) ** 2).sum() / (3.0 * px)
        if lpips is not None:
            dmap = torch.stack([lpips.spatial(rgb[i].permute(1, 2, 0), gt[i].permute(1, 2, 0)) for i in range(t)])
            return mse, (dmap.to(rgb.dtype) * m[:, 0]).sum() / px
        dmap = 1.0 - torch.stack([ssim_map(rgb[i].permute(1, 2, 0), gt[i].permute(1, 2, 0)) for i in range(t)])
        r = (m.shape[-1] - dmap.shape[-1]) // 2  # SSIM's map covers where its window fits: the mask there
        mv = m[:, 0, r : m.shape[-2] - r, r : m.shape[-1] - r]
        return mse, (dmap * mv).sum() / mv.sum().clamp_min(1.0)
    mse = ((rgb - gt) ** 2).mean()
    if lpips is not None:
        return mse, lpips(rgb, gt).mean()
    ssim = torch.stack([ssim_map(rgb[i].permute(1, 2, 0), gt[i].permute(1, 2, 0)).mean() for i in range(t)])
    return mse, 1.0 - ssim.mean()


def training_loss(
    pred: PairPrediction, batch: dict[str, torch.Tensor], config: LossConfig, lpips: LPIPS | None = None
) -> LossTerms:
    """``L_photo + λ_MAC · L_MAC`` averaged over the samples of ``batch`` (module docstring).

    Args:
        pred: the predictor's outputs for the batch's context pairs (with Gaussian maps).
        batch: ``context [B, 2, 3, H, W]``, ``context_c2w [B, 2, 4, 4]``, ``target [B, T, 3, H, W]``,
            ``target_K [B, T, 3, 3]``, ``target_c2w [B, T, 4, 4]``, optionally ``target_mask [B, T, H, W]``, or
            ``target_depth [B, T, H, W]`` and ``context_depth [B, 2, H, W]`` (+ ``context_K``) for :func:`loss_masks`.
        config: the weights.
        lpips: an LPIPS model (inputs in [0, 1]); None: D-SSIM instead.
    """
    if pred.gaussians is None:
        raise ValueError("training needs the Gaussian head's outputs")
    target = batch["target"].to(pred.pts3d.device)
    n, t, _, h, w = target.shape
    mask = batch.get("target_mask")
    if mask is None and "target_depth" in batch and "context_depth" in batch:
        mask = loss_masks(batch)
    totals = {"photo": 0.0, "mse": 0.0, "perceptual": 0.0, "mac": 0.0, "matches": 0.0}
    losses = []
    for b in range(n):
        rgb = render_targets(
            pred.gaussians, b, batch["target_K"][b], batch["target_c2w"][b], batch["context_c2w"][b, 0], (h, w),
            config.background, config.near_plane,
        )  # fmt: skip
        mse, perceptual = _photometric(rgb, target[b].to(rgb.dtype), None if mask is None else mask[b], config, lpips)
        photo = mse + (config.lpips_weight if lpips is not None else config.ssim_weight) * perceptual
        loss = photo
        if config.mac_weight > 0:
            xy0, xy1, weight = sample_matches(pred.desc[b], pred.desc_conf[b], config)
            if len(xy0):
                dev, dt = pred.gaussians[0].means.device, pred.gaussians[0].means.dtype
                c2w0 = batch["context_c2w"][b, 0].to(device=dev, dtype=dt)[None]
                mac = mac_loss(
                    pred.gaussians[0].view(b), pred.gaussians[1].view(b), xy0.to(dev), xy1.to(dev),
                    torch.zeros(len(xy0), dtype=torch.long, device=dev), weight.to(device=dev, dtype=dt),
                    c2w0, c2w0, config.mac, check_inputs=False,
                )  # fmt: skip
                loss = loss + config.mac_weight * mac.loss
                totals["mac"] += float(mac.loss.detach())
            totals["matches"] += len(xy0)
        if config.geometry_weight > 0 and "context_depth" in batch:
            geo = point_regression(
                pred.pts3d[b], batch["context_depth"][b], batch["context_K"][b], batch["context_c2w"][b]
            )
            if geo is not None:
                loss = loss + config.geometry_weight * geo
        losses.append(loss)
        totals["photo"] += float(photo.detach())
        totals["mse"] += float(mse.detach())
        totals["perceptual"] += float(perceptual.detach())
    return LossTerms(loss=torch.stack(losses).mean(), **{k: v / n for k, v in totals.items()})
