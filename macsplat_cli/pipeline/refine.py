"""Stage 7: MAC-regularised test-time refinement of a two-view reconstruction (``--refine``).

The Gaussians of both views (per-pixel maps, optionally pooled ``scale × scale`` for
speed) are optimised with Adam so that they render the two context photos well, and —
with the MAC loss — so that matched pixels of the two views agree on one Gaussian:

``L = Σ_views [ L2 + w_ssim · (1 − SSIM) (+ w_lpips · LPIPS) ] + λ_MAC · L_MAC``

(LPIPS only with user-supplied VGG weights, :func:`macsplat_cli.lpips.load_lpips`.)

over means, scales, rotations, opacities and colours (the cameras are fixed). It stops
early once the loss plateaus (relative improvement of its running mean below
``plateau_tol`` over ``plateau_window`` steps). Measured: benchmarks/history/refine.md.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from ..errors import InputError
from ..gaussians import GaussianMaps, Gaussians
from ..mac import mac_loss
from ..metrics import SsimTarget, ssim_map, ssim_target
from ..render import render
from ..report import RefineReport
from ..rotations import quat_multiply, rotmat_to_quat_np
from .refine_adam import Adam
from .refine_config import AUTO_STEPS, RefineConfig
from .types import DepthMap, MatchSet, TwoViewGeometry, View

if TYPE_CHECKING:
    from .run import Reconstruction

__all__ = [
    "AUTO_STEPS", "RefineConfig", "RefineResult", "check_scale", "refine", "refine_reconstruction", "run_steps",
]  # fmt: skip

logger = logging.getLogger(__name__)

RefineStep = Callable[[int, int, dict[str, float]], None]
"""Called after each refinement step with the step (from 1), the most steps the refinement runs, and its loss terms."""

SSIM_WEIGHT = 0.2
"""Weight of the D-SSIM term beside L2 (3DGS uses 0.2 with L1; first default, benchmarks/history/refine.md)."""
LPIPS_WEIGHT = 0.25
"""Weight of the LPIPS term when an LPIPS model is given (Splatt3R's training loss)."""
DENSE_STRIDE = 4
"""Pixel step of the dense MAC matches (``mac_matches="dense"``, the ablation of benchmarks/history/refine.md)."""
LR_MEANS, LR_LOG_SCALES, LR_QUATS, LR_OPACITY, LR_SH = 1e-3, 5e-3, 2e-3, 3e-2, 5e-3
"""Adam's learning rates of the means (a fraction of the median scene depth), log-scales, quaternions, opacity
logits and SH coefficients (3DGS's, scaled to a per-pixel initialisation; benchmarks/history/refine.md)."""
LR_SCALE = 1.5
"""Every rate above times this: with the cosine fall to :data:`LR_FINAL`, 25 steps keep the gain of 50 at constant
rates (benchmarks/history/refine.md)."""
LR_FINAL = 0.3
"""The rates fall (cosine) to this fraction of their start by the last step (benchmarks/history/refine.md)."""


@dataclass
class RefineResult:
    """The refined per-view maps (``B = 1`` each, at the refinement resolution) and the loss history; ``poses``: the
    refined camera-to-world [4, 4] of each map's camera when the poses were refined too (more than two photos,
    :mod:`.multiview.joint`), else None."""

    maps: list[GaussianMaps]
    steps: int
    seconds: float
    stopped_early: bool
    history: list[dict[str, float]]
    poses: list[np.ndarray] | None = None


@dataclass
class _Target:
    """One view as the loss sees it: its photo at the refinement resolution (and its SSIM statistics, blurred once)
    and the camera rendering it."""

    image: torch.Tensor  # [h, w, 3] float32
    world_to_cam: torch.Tensor  # [4, 4] float32
    K: torch.Tensor  # [3, 3] float32, intrinsics at the refinement resolution
    ssim: SsimTarget

    def render(self, world: Gaussians) -> torch.Tensor:
        """``world`` seen by this view's camera. [h, w, 3]"""
        h, w = self.image.shape[:2]
        return render(world, self.world_to_cam, self.K, w, h).rgb


@dataclass
class _MacMatches:
    """One pair's MAC matches at the refinement resolution."""

    a: int
    b: int
    xy0: torch.Tensor  # [M, 2] float32
    xy1: torch.Tensor  # [M, 2] float32
    weights: torch.Tensor  # [M] float32
    batch: torch.Tensor  # [M] int64, zeros (one pair)
    cam_to_world: tuple[torch.Tensor, torch.Tensor]  # [1, 4, 4] float32 each


@dataclass
class _World:
    """How a step turns one view's map into world Gaussians: :meth:`GaussianMaps.to_gaussians`'s values and
    arithmetic, with what does not change between steps found once (the valid pixels' indices, the pose's rotation,
    translation and quaternion) and the pose skipped where it is exactly the identity (moving by it changes no
    value)."""

    sel: torch.Tensor | None  # [n] int64, the valid pixels (row-major); None: every pixel
    R: torch.Tensor | None  # [3, 3] in the maps' dtype; None: the identity
    t: torch.Tensor | None  # [3]
    q: torch.Tensor | None  # [4], the quaternion of R

    @staticmethod
    def of(m: GaussianMaps) -> _World:
        """``m``'s (``B = 1``) indices and pose."""
        sel = None if m.valid is None else m.valid[0].reshape(-1).nonzero().squeeze(1)
        c2w = m.cam_to_world
        if c2w is None or torch.equal(c2w[0], torch.eye(4, dtype=c2w.dtype, device=c2w.device)):
            return _World(sel, None, None, None)
        T = c2w[0].to(device=m.device, dtype=m.dtype)
        q = rotmat_to_quat_np(T[:3, :3].detach().cpu().double().numpy())
        return _World(sel, T[:3, :3], T[:3, 3], torch.as_tensor(q, dtype=m.dtype, device=m.device))

    def gaussians(self, m: GaussianMaps) -> Gaussians:
        """``m.to_gaussians()`` (differentiable w.r.t. the five maps)."""
        flat = [t[0].reshape(-1, *t.shape[3:]) for t in m.tensors()]
        if self.sel is not None:
            flat = [t.index_select(0, self.sel) for t in flat]
        means, log_scales, quats, opacity_logits, sh = flat
        if self.R is not None and self.t is not None and self.q is not None:
            means = means @ self.R.T + self.t
            quats = quat_multiply(self.q.expand(quats.shape[0], 4), quats)
        return Gaussians(means, log_scales, quats, opacity_logits, sh)


def _downscale(image: np.ndarray, factor: int) -> torch.Tensor:
    h, w = image.shape[:2]
    if factor == 1:
        return torch.from_numpy(np.ascontiguousarray(image, np.float32))
    small = cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(small, np.float32))


def _cam_to_world(m: GaussianMaps) -> torch.Tensor:
    """A one-view map's camera-to-world transform (the identity when it has none). [4, 4], as stored"""
    if m.batch != 1:
        raise InputError(f"refine() takes one map per view (B = 1), got B = {m.batch}")
    return m.cam_to_world_or_identity()[0]


def _targets(views: list[View], Ks: list[np.ndarray], params: list[GaussianMaps], f: int) -> list[_Target]:
    """Each view's photo at 1/``f`` and its camera (the intrinsics ``Ks`` scaled by 1/``f``)."""
    targets = []
    for k, (v, K) in enumerate(zip(views, Ks)):
        img = _downscale(v.image, f)
        K = K.copy()
        K[:2] /= f
        w2c = torch.linalg.inv(_cam_to_world(params[k])).float()
        targets.append(_Target(img, w2c, torch.tensor(K, dtype=torch.float32), ssim_target(img)))
    return targets


def _scene_depth(params: list[GaussianMaps]) -> float:
    """The median depth of the valid Gaussians in their cameras' frames (1 with none): the scene's scale."""
    depth = torch.cat([m.means[..., 2][m.valid_mask()] for m in params]).detach()
    return float(depth.median()) if depth.numel() else 1.0


def _optimizer(params: list[GaussianMaps], cfg: RefineConfig, scene: float, means_rate: float = 1.0) -> Adam:
    """Adam (:mod:`.refine_adam`) over the five parameter maps; the means' rate scaled by the scene's depth
    (:func:`_scene_depth`) and ``means_rate``."""
    s = LR_SCALE
    opt = Adam(
        [
            {"params": [m.means for m in params], "lr": s * LR_MEANS * scene * means_rate},
            {"params": [m.log_scales for m in params], "lr": s * LR_LOG_SCALES},
            {"params": [m.quats for m in params], "lr": s * LR_QUATS},
            {"params": [m.opacity_logits for m in params], "lr": s * LR_OPACITY},
            {"params": [m.sh for m in params], "lr": s * LR_SH},
        ]
    )
    for group in opt.param_groups:
        group["initial_lr"] = group["lr"]
    return opt


def _set_learning_rates(opt: Adam, step: int, cfg: RefineConfig) -> None:
    """Cosine from the initial rates (step 1) to :data:`LR_FINAL` of them (step ``cfg.steps``)."""
    if LR_FINAL == 1.0 or cfg.steps <= 1:
        return
    f = LR_FINAL + (1.0 - LR_FINAL) * 0.5 * (1.0 + math.cos(math.pi * (step - 1) / (cfg.steps - 1)))
    for group in opt.param_groups:
        group["lr"] = group["initial_lr"] * f


def run_steps(
    opt: Adam, cfg: RefineConfig, step_loss: Callable[[int], tuple[torch.Tensor, dict[str, float]]],
    stop: Callable[[list[dict[str, float]], int], bool], on_step: RefineStep | None,
) -> tuple[list[dict[str, float]], int, bool]:  # fmt: skip
    """The refinement's loop (this module's and :mod:`.multiview.joint`'s): up to ``cfg.steps`` Adam steps on
    ``step_loss(step)`` (the loss and its terms) at the cosine rates (:func:`_set_learning_rates`), each step's
    terms reported to ``on_step``, until ``stop(history, step)``. Returns the terms of every step, the steps run
    and whether it stopped before ``cfg.steps``."""
    history: list[dict[str, float]] = []
    step = 0
    for step in range(1, cfg.steps + 1):
        opt.zero_grad(set_to_none=True)
        _set_learning_rates(opt, step, cfg)
        loss, terms = step_loss(step)
        loss.backward()
        opt.step()
        history.append(terms)
        if on_step is not None:
            on_step(step, cfg.steps, terms)
        if stop(history, step):
            return history, step, step < cfg.steps
    return history, step, False


def _pair_matches(geometry: TwoViewGeometry, depths: list[DepthMap] | None, cfg: RefineConfig) -> list[MatchSet]:
    """The two views' verified matches (and with ``mac_matches="dense"`` the depth-consistent pixels)."""
    m_xy0, m_xy1, m_w = geometry.inliers.xy0, geometry.inliers.xy1, geometry.inliers.conf
    if cfg.mac_matches == "dense" and depths is not None:
        d_xy0, d_xy1, d_w = _dense_matches(geometry, depths, DENSE_STRIDE)
        m_xy0, m_xy1, m_w = np.concatenate([m_xy0, d_xy0]), np.concatenate([m_xy1, d_xy1]), np.concatenate([m_w, d_w])
    return [MatchSet(0, 1, m_xy0, m_xy1, m_w)]


def _mac_matches(sets: list[MatchSet], params: list[GaussianMaps], cfg: RefineConfig) -> list[_MacMatches]:
    """Each match set at 1/``scale``, with its two views' poses."""
    f = cfg.scale
    return [
        _MacMatches(
            a=m.a,
            b=m.b,
            xy0=torch.tensor(m.xy_a / f, dtype=torch.float32),
            xy1=torch.tensor(m.xy_b / f, dtype=torch.float32),
            weights=torch.tensor(m.weights, dtype=torch.float32),
            batch=torch.zeros(len(m.xy_a), dtype=torch.long),
            cam_to_world=(_cam_to_world(params[m.a]).float()[None], _cam_to_world(params[m.b]).float()[None]),
        )
        for m in sets
        if len(m.xy_a)
    ]


def _step_loss(
    params: list[GaussianMaps], targets: list[_Target], matches: list[_MacMatches], cfg: RefineConfig,
    lpips: torch.nn.Module | None, worlds: list[_World],
) -> tuple[torch.Tensor, dict[str, float]]:  # fmt: skip
    """One step's loss (photometric over every view, + LPIPS, + λ_MAC · MAC over every pair) and its terms;
    ``worlds``: each map's :class:`_World`."""
    world = Gaussians.cat([w.gaussians(m) for w, m in zip(worlds, params)])
    photo = torch.zeros(())
    perceptual = torch.zeros(())
    for t in targets:
        rgb = t.render(world)
        photo = photo + ((rgb - t.image) ** 2).mean() + SSIM_WEIGHT * (1.0 - ssim_map(rgb, t.ssim).mean())
        if lpips is not None:
            perceptual = perceptual + lpips(rgb, t.image)
    terms = {"photo": float(photo.detach())}
    if lpips is not None:
        terms["lpips"] = float(perceptual.detach())
        photo = photo + LPIPS_WEIGHT * perceptual
    loss = photo
    if cfg.use_mac and matches:
        # every pair's MAC loss, averaged over the pairs (one pair: exactly the two-view loss)
        parts = [
            mac_loss(
                params[m.a], params[m.b], m.xy0, m.xy1, m.batch, m.weights, *m.cam_to_world, cfg.mac, check_inputs=False
            )  # fmt: skip
            for m in matches
        ]
        n = len(parts)
        mac, pos, shape = (sum(getattr(p, k) for p in parts) / n for k in ("loss", "position", "shape"))
        loss = loss + cfg.mac.weight * mac
        terms.update(mac=float(mac.detach()), mac_pos=float(pos.detach()), mac_shape=float(shape.detach()))
    terms["loss"] = float(loss.detach())
    return loss, terms


def _plateaued(running: list[float], step: int, cfg: RefineConfig) -> bool:
    """The running-mean loss improved by less than ``plateau_tol`` over the last ``plateau_window`` steps."""
    if step < max(cfg.min_steps, 2 * cfg.plateau_window):
        return False
    recent = float(np.mean(running[-cfg.plateau_window :]))
    before = float(np.mean(running[-2 * cfg.plateau_window : -cfg.plateau_window]))
    return before - recent < cfg.plateau_tol * abs(before)


def refine(
    views: list[View],
    geometry: TwoViewGeometry | None,
    maps: list[GaussianMaps],
    config: RefineConfig | None = None,
    *,
    depths: list[DepthMap] | None = None,
    lpips: torch.nn.Module | None = None,
    on_step: RefineStep | None = None,
    match_sets: list[MatchSet] | None = None,
) -> RefineResult:
    """Refine every view's Gaussians on its photo (+ the MAC loss over the matched pairs).

    Args:
        views: the views (photos at the working resolution; with no ``geometry``, their ``K``).
        geometry: two views' relative pose; its verified matches feed the MAC loss. None: more views, matched by
            ``match_sets``.
        maps: the per-view Gaussians to refine, ``B = 1`` each, in their view's camera frame with
            ``cam_to_world`` set (None: the identity) (not modified).
        config: settings (None: :data:`AUTO_STEPS` steps, the other settings their defaults).
        depths: the views' depth maps (needed for ``mac_matches="dense"``).
        lpips: an LPIPS model (:class:`macsplat_cli.lpips.LPIPS`) adds its term to the photometric loss.
        on_step: called after each step with the step number and the loss terms.
        match_sets: the MAC loss's matches when there is no ``geometry`` (any pairs of the views).

    Returns:
        :class:`RefineResult` with maps at ``1/scale`` of the working resolution.
    """
    cfg = config or RefineConfig(steps=AUTO_STEPS)
    params = [m.pooled(cfg.scale).detach() for m in maps]
    for m in params:
        for t in m.tensors():
            t.requires_grad_(True)
    Ks = [geometry.K0, geometry.K1] if geometry is not None else [v.K for v in views]
    targets = _targets(views, Ks, params, cfg.scale)
    opt = _optimizer(params, cfg, _scene_depth(params))
    sets = _pair_matches(geometry, depths, cfg) if geometry is not None else list(match_sets or [])
    matches = _mac_matches(sets, params, cfg)
    worlds = [_World.of(m) for m in params]

    t0 = time.perf_counter()
    history, step, stopped_early = run_steps(
        opt, cfg, lambda step: _step_loss(params, targets, matches, cfg, lpips, worlds),
        lambda history, step: _plateaued([h["loss"] for h in history], step, cfg), on_step,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    logger.debug(
        "refinement: %d steps in %.1f s, loss %.4f → %.4f", step, seconds, history[0]["loss"], history[-1]["loss"]
    )
    return RefineResult(
        maps=[m.detach() for m in params], steps=step, seconds=seconds, stopped_early=stopped_early, history=history
    )


def check_scale(maps: list[GaussianMaps], scale: int) -> None:
    """Raise :class:`~macsplat_cli.errors.InputError` when the maps' size is not divisible by ``scale``."""
    h, w = maps[0].size
    if any(m.size[0] % scale or m.size[1] % scale for m in maps):
        raise InputError(f"--refine-scale {scale}: the working size {w}x{h} is not divisible by it")


def refine_reconstruction(
    rec: Reconstruction, config: RefineConfig, *, lpips: torch.nn.Module | None = None,
    on_step: RefineStep | None = None,
) -> tuple[RefineResult, RefineReport]:  # fmt: skip
    """:func:`refine` on a finished reconstruction (its views, pose, maps and depths), and its report section.

    Raises:
        InputError: the working size is not divisible by ``config.scale`` (:func:`check_scale`).
    """
    check_scale(rec.maps, config.scale)
    f = config.scale
    sets = rec.multiview.match_sets() if rec.multiview is not None else None
    pair = rec.pose.geometry if rec.multiview is None and rec.pose is not None else None  # a pair: its matches
    out = refine(rec.views, pair, rec.maps, config, depths=rec.depths, lpips=lpips, on_step=on_step,
                 match_sets=sets)  # fmt: skip
    report = RefineReport(
        steps=out.steps,
        max_steps=config.steps,
        stopped_early=out.stopped_early,
        seconds=out.seconds,
        scale=f,
        mac=config.use_mac,
        lpips=lpips is not None,
        loss_first=out.history[0],
        loss_last=out.history[-1],
    )
    return out, report


def _dense_matches(geometry: TwoViewGeometry, depths: list[DepthMap], stride: int) -> tuple[np.ndarray, ...]:
    """Measured pixels of view 0 (every ``stride``-th) and their depth-consistent pixels in view 1."""
    d0, d1 = depths
    m0 = d0.measured if d0.measured is not None else d0.valid
    h, w = d0.depth.shape
    ys, xs = np.mgrid[0:h:stride, 0:w:stride]
    ys, xs = ys.ravel(), xs.ravel()
    keep = m0[ys, xs]
    ys, xs = ys[keep], xs[keep]
    xy0 = np.stack([xs + 0.5, ys + 0.5], 1)
    z = d0.depth[ys, xs].astype(np.float64)
    X = (np.concatenate([xy0, np.ones((len(xy0), 1))], 1) @ np.linalg.inv(geometry.K0).T) * z[:, None]
    X1 = X @ geometry.R.T + geometry.t
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (X1 @ geometry.K1.T)[:, :2] / X1[:, 2:3]
    h1, w1 = d1.depth.shape
    ok = np.isfinite(uv).all(1) & (X1[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w1) & (uv[:, 1] >= 0) & (uv[:, 1] < h1)
    u, v = np.floor(uv[ok, 0]).astype(int), np.floor(uv[ok, 1]).astype(int)
    m1 = d1.measured if d1.measured is not None else d1.valid
    agree = m1[v, u] & (np.abs(d1.depth[v, u] - X1[ok, 2]) < 0.02 * X1[ok, 2])
    idx = np.flatnonzero(ok)[agree]
    conf = (d0.confidence[ys[idx], xs[idx]] * d1.confidence[v[agree], u[agree]]).astype(np.float32)
    return xy0[idx], uv[idx], conf
