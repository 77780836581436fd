"""Joint refinement of the Gaussians and the camera poses over every registered photo (issue 41).

"Gaussian bundle adjustment" (InstantSplat): the pixel Gaussians of every registered photo and each camera's pose are
optimised together (Adam) on the photometric loss of the photos, ``L2 + w_ssim · (1 − SSIM)``, one photo a step in
turn (:data:`PHOTOS_PER_STEP`, as 3DGS trains), plus ``λ_MAC · MAC`` over the verified matches of every matched pair
of photos (:func:`macsplat_cli.mac.mac_loss`) while a camera is free to move (with every pose held, the term only
pulls the matched Gaussians onto their match rays: measured −0.2 dB and a third of the step's time).

Poses: each camera ``k`` gets a small update, a rotation ``ω_k`` (axis-angle, world frame) and a centre shift
``δ_k``: ``R'_k = Exp(ω_k) R_k``, ``c'_k = c_k + δ_k``, with their own learning rates (:data:`LR_ROTATION`,
:data:`LR_CENTRE`). A photo's Gaussians ride with its camera (they were built from its depth at its pose): map
``k``'s world Gaussians move by the camera's motion, so a photo's own render does not depend on its pose and the
poses are set by what the other photos see of its Gaussians (and the MAC matches). The gauge is fixed: camera 0
(the world frame) does not move, and the scale camera (the first other one) keeps its distance to camera 0.

Poses the matches already fix stay still (:func:`trusted_cameras`): a camera whose verified matches with a camera
already trusted (camera 0 first) lie within :data:`POSE_TRUST_PX` refinement pixels of their epipolar lines (median
Sampson distance) is not moved. The photometric optimum of a pose at the refinement's resolution, with Gaussians
pooled from estimated depths, lies a few tenths of a degree from the truth (measured on exact cameras and depths:
25 steps moved them 0.24° and 0.51°; on a 4-photo orbit 0.02° → 0.23°), so a sub-pixel registration is better left
as it is; a camera degrees off (its matches pixels off their lines) is refined. The matches of a reconstruction are
the registration's own tracks, so this trusts a registration whose bundle adjustment fits them to sub-pixel (it says
nothing of an error along the epipolar lines, nor of a wrong pose its own tracks agree with).

Stopping on held-out evidence: a share of every photo's pixels (:data:`HOLDOUT_SHARE`, fixed seed) is left out of
the loss (their target is the render itself, so neither the L2 nor the SSIM term sees them); the curve is the mean of
each photo's held-out error when it was last rendered, and the run stops once it has not fallen by
:data:`HOLDOUT_TOL` for :data:`HOLDOUT_PATIENCE` steps (a round of every photo at least), and reports the curve.

What is optimised is each photo's valid Gaussians, packed (:mod:`.packed`: the optimiser and the gradients follow
the Gaussians the co-visibility init kept, not the pixels), and a photo's step renders only the Gaussians that may
fall on it (tested once, with a margin: the same image as the whole scene's), so a step's cost follows what its
photo sees.

The renders go through the fused kernel, which takes no camera gradient: camera ``j``'s update is applied to the
Gaussians instead (``Y = Exp(−ω_j)(X − c'_j) + c_j``, rendered by the unrefined camera), the same image. A map's
registered pose, its camera's update and the rendering camera's inverse update are composed into one rigid motion
per map and step (:func:`.packed.placements`, float64), applied to its Gaussians once. Measured:
benchmarks/history/multiview_joint.md and (speed) benchmarks/history/refine.md.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...gaussians import GaussianMaps
from ...mac import mac_loss
from ...metrics import ssim_map
from ...render import render
from ...report import RefineReport
from ...rotations import quat_to_rotmat
from ..refine import (
    SSIM_WEIGHT,
    RefineConfig,
    RefineResult,
    RefineStep,
    _downscale,
    _optimizer,
    _scene_depth,
    run_steps,
)
from ..types import MatchSet, View

if TYPE_CHECKING:
    from ..run import Reconstruction
from .packed import Frames, Packed, centres, frames_of, in_view, indices, placed, placements
from .sh_views import view_dependent

__all__ = ["JointResult", "joint_reconstruction", "joint_refine", "trusted_cameras"]

logger = logging.getLogger(__name__)

LR_ROTATION = 2e-3
"""Adam's step on a camera's rotation, radians (0.11° a step at most: a registration error of a few tenths of a
degree is gone in a few steps)."""
LR_CENTRE = 1e-3
"""Adam's step on a camera's centre, as a fraction of the median scene depth."""
POSE_TRUST_PX = 0.5
"""A camera whose matches with a trusted camera lie within this many refinement pixels of their epipolar lines
(median) keeps its registered pose: half a pixel is below what the photometric refinement at that resolution places
(a pixel at 1/2 of a 512-px, 60° photo is 0.23°)."""
HOLDOUT_SHARE = 1 / 16
"""The share of every photo's pixels held out of the loss (their error decides when to stop)."""
HOLDOUT_TOL = 1e-3
"""The held-out error must fall by this fraction of its best to count as falling."""
HOLDOUT_PATIENCE = 5
"""Steps without the held-out error falling before the refinement stops (at least one per photo)."""
MIN_STEPS = 8
"""Never stop before this many steps (the first steps move the Gaussians more than the error shows)."""
FULL_RESOLUTION_MEANS_RATE = 0.5
"""At full resolution (``scale`` 1: ``best`` on three photos or more) the means' learning rate is the pooled
refinement's times this (a step of the same pixels: a pixel is half as wide). Room 4, 10 steps, mid / side: 21.52 /
20.22 dB at the pooled rates, 22.05 / 20.54 with the means' halved, 21.98 / 20.50 with every Gaussian rate halved,
21.45 / 20.17 with every one but the means' (benchmarks/history/multiview_joint.md)."""
SH_DEGREE = 1
"""The SH degree of the Gaussians enough photos see from spread directions (:mod:`.sh_views`); 0 elsewhere."""
PHOTOS_PER_STEP = 1
"""Photos rendered each step, in turn (:func:`_schedule`; 3DGS's one view a step). A photo's render costs the same
whichever photo it is (every photo sees most of the Gaussians), so steps of one photo buy more updates for the
time: on the 4-photo orbits, 40 one-photo steps matched or beat 25 steps of all four at 0.5× the CPU time
(benchmarks/history/multiview_joint.md)."""
RENDERS_PER_STEP = 0.4
"""Renders of each photo per step asked (``--refine 25``, ``best``'s: 10 of each, 40 one-photo steps on 4 photos,
80 on 8): 4 photos × 0.4 fits ``best``'s time there; 8 photos at 40 steps stayed 0.37 dB below their middle pair
at its views, at 80 0.15 dB above (benchmarks/history/multiview_joint.md)."""


@dataclass
class JointResult:
    """The refined maps (each in its camera's frame, ``cam_to_world`` the refined pose, ``1/scale`` resolution),
    the refined poses and the run.

    Attributes:
        maps: the refined Gaussians, one map per input map (``B = 1``).
        poses: each camera's refined camera-to-world. [4, 4] float64
        rotation_change_deg: how far each camera turned. [C]
        steps: steps run; stopped_early: the held-out error stopped falling before ``config.steps``.
        poses_refined: which cameras were free to move (not fixed, not trusted: :func:`trusted_cameras`).
        mac: whether the MAC term was in the loss (asked for, and a camera free to move).
        history: each step's loss terms (``heldout``: the held-out pixels' mean squared error).
    """

    maps: list[GaussianMaps]
    poses: list[np.ndarray]
    rotation_change_deg: list[float]
    steps: int
    seconds: float
    stopped_early: bool
    history: list[dict[str, float]]
    poses_refined: list[bool]
    mac: bool = False

    def report(self) -> dict[str, object]:
        """The refinement report's ``joint`` section: steps, the held-out curve, the poses' changes."""
        return {
            "steps": self.steps,
            "stopped_on_heldout": self.stopped_early,
            "heldout_mse": [round(h["heldout"], 6) for h in self.history],
            "rotation_change_deg": [round(r, 4) for r in self.rotation_change_deg],
            "poses_refined": self.poses_refined,
        }


def _axis_quat(w: torch.Tensor) -> torch.Tensor:
    """The unit quaternion (w, x, y, z) of axis-angle vectors (smooth at 0). [..., 3] → [..., 4]"""
    theta = torch.sqrt((w * w).sum(-1, keepdim=True) + 1e-30)
    return torch.cat([torch.cos(theta / 2), 0.5 * torch.sinc(theta / (2 * torch.pi)) * w], -1)


class _Poses(torch.nn.Module):
    """Every camera's small pose update and the gauge (camera ``fixed`` still, ``scale_camera``'s distance kept)."""

    def __init__(self, cam_to_world: list[np.ndarray], fixed: int) -> None:
        super().__init__()
        T = torch.as_tensor(np.stack(cam_to_world), dtype=torch.float64)
        self.R0, self.c0 = T[:, :3, :3], T[:, :3, 3]
        self.omega = torch.nn.Parameter(torch.zeros(len(T), 3, dtype=torch.float64))
        self.delta = torch.nn.Parameter(torch.zeros(len(T), 3, dtype=torch.float64))
        self.free = torch.ones(len(T), 1, dtype=torch.float64)
        self.free[fixed] = 0.0
        others = [k for k in range(len(T)) if k != fixed]
        self.fixed = fixed
        self.scale_camera = others[0] if others else None
        self.baseline = float((self.c0[others[0]] - self.c0[fixed]).norm()) if others else 0.0

    def current(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each camera's rotation update as a quaternion [C, 4] and its refined centre [C, 3]."""
        q = _axis_quat(self.omega * self.free)
        c = self.c0 + self.delta * self.free
        s = self.scale_camera
        if s is not None and self.baseline > 0:
            d = c[s] - c[self.fixed]
            c = torch.cat([c[:s], (c[self.fixed] + self.baseline * d / d.norm())[None], c[s + 1 :]])
        return q, c

    def cam_to_world(self) -> torch.Tensor:
        """The refined camera-to-world transforms. [C, 4, 4] float64"""
        q, c = self.current()
        T = torch.eye(4, dtype=torch.float64).repeat(len(q), 1, 1)
        T[:, :3, :3] = quat_to_rotmat(q) @ self.R0
        T[:, :3, 3] = c
        return T


def _epipolar_px(m: MatchSet, Ks: list[np.ndarray], cam_to_world: list[np.ndarray]) -> float:
    """The median Sampson distance (px, working resolution) of a pair's matches to the poses' epipolar geometry."""
    Ta, Tb = cam_to_world[m.a], cam_to_world[m.b]
    R = Tb[:3, :3].T @ Ta[:3, :3]
    t = Tb[:3, :3].T @ (Ta[:3, 3] - Tb[:3, 3])
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(Ks[m.b]).T @ tx @ R @ np.linalg.inv(Ks[m.a])
    xa = np.c_[m.xy_a, np.ones(len(m.xy_a))]
    xb = np.c_[m.xy_b, np.ones(len(m.xy_b))]
    Fa, Fb = xa @ F.T, xb @ F
    num = np.einsum("ij,ij->i", xb, Fa) ** 2
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2
    return float(np.median(np.sqrt(num / np.maximum(den, 1e-300))))


def trusted_cameras(
    sets: list[MatchSet], Ks: list[np.ndarray], cam_to_world: list[np.ndarray], fixed: int, tol_px: float
) -> list[bool]:
    """Which cameras the matches already fix: ``fixed``, then (repeatedly) every camera whose matches with a trusted
    one lie within ``tol_px`` (working-resolution pixels, median Sampson distance) of their epipolar lines.

    Args:
        sets: the verified matches of each matched pair (pixels at the working resolution).
        Ks: each camera's intrinsics at the working resolution. [3, 3]
        cam_to_world: each camera's registered pose. [4, 4]
    """
    centres = [T[:3, 3] for T in cam_to_world]
    tested = [m for m in sets if len(m.xy_a) >= 8 and np.any(centres[m.a] != centres[m.b])]  # a baseline to test
    err = {(m.a, m.b): _epipolar_px(m, Ks, cam_to_world) for m in tested}
    trusted = [k == fixed for k in range(len(cam_to_world))]
    grew = True
    while grew:
        grew = False
        for (a, b), e in err.items():
            if e <= tol_px and trusted[a] != trusted[b]:
                trusted[a] = trusted[b] = grew = True
    return trusted


@dataclass
class _Photo:
    """One camera's photo at the refinement resolution, its held-out pixels and its unrefined camera."""

    image: torch.Tensor  # [h, w, 3]
    heldout: torch.Tensor  # [h, w] bool
    world_to_cam: torch.Tensor  # [4, 4] float32
    K: torch.Tensor  # [3, 3] float32


def _photos(views: list[View], Ks: list[np.ndarray], cam_to_world: list[np.ndarray], f: int) -> list[_Photo]:
    gen = torch.Generator().manual_seed(0)
    out = []
    for v, K, T in zip(views, Ks, cam_to_world):
        img = _downscale(v.image, f)
        K = K.copy()
        K[:2] /= f
        held = torch.rand(img.shape[:2], generator=gen) < HOLDOUT_SHARE
        out.append(_Photo(img, held, torch.as_tensor(np.linalg.inv(T), dtype=torch.float32),
                          torch.as_tensor(K, dtype=torch.float32)))  # fmt: skip
    return out


_MacSet = tuple[int, int, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
"""One pair's MAC matches: maps ``a``, ``b``; pixels [M, 2] of each at the refinement resolution; weights [M]; the
batch index [M] (zeros)."""


def _mac_sets(sets: list[MatchSet], params: list[GaussianMaps], f: int) -> list[_MacSet]:
    """Each pair's matches at ``1/f``, weighted 0 where either end's Gaussian is no longer valid."""
    out: list[_MacSet] = []
    for m in sets:
        if not len(m.xy_a):
            continue
        xa = torch.as_tensor(m.xy_a / f, dtype=torch.float32)
        xb = torch.as_tensor(m.xy_b / f, dtype=torch.float32)
        w = torch.as_tensor(m.weights, dtype=torch.float32).clone()
        for x, p in ((xa, params[m.a]), (xb, params[m.b])):
            h, wd = p.size
            col = x[:, 0].floor().long().clamp(0, wd - 1)
            row = x[:, 1].floor().long().clamp(0, h - 1)
            w = w * p.valid_mask()[0, row, col].float()
        out.append((m.a, m.b, xa, xb, w, torch.zeros(len(xa), dtype=torch.long)))
    return out


def _loss(
    params: list[GaussianMaps],
    poses: _Poses,
    photos: list[_Photo],
    which: list[int],
    mac_sets: list[_MacSet],
    cfg: RefineConfig,
    visible: list[list[torch.Tensor | bool | None]],
    packs: list[Packed],
    frames: Frames,
) -> tuple[torch.Tensor, dict[int, float], dict[str, float]]:
    """One step's loss over the photos ``which`` (and the MAC loss over every matched pair), each rendered photo's
    held-out error, and the terms. Photo ``k`` renders the Gaussians ``visible[k]`` alone (per map: the indices of
    the leaves :func:`.packed.in_view` kept (:func:`.packed.indices`), True for all, None for none); a map it does
    not see gets no gradient from it. ``params`` are the packed leaves (``packs``: the MAC term samples their pixel
    maps), ``frames`` their registered poses (:func:`.packed.frames_of`)."""
    with torch.set_grad_enabled(bool(poses.free.any())):  # every pose held: no pose gradients to compute
        q, c = poses.current()
    photo = torch.zeros(())
    held: dict[int, float] = {}
    for k in which:
        p = photos[k]
        motion = placements(frames, q, c, poses.c0, poses.fixed, k, params[0].dtype)
        seen = placed(params, visible[k], motion)
        h, w = p.image.shape[:2]
        rgb = render(seen, p.world_to_cam, p.K, w, h).rgb
        target = torch.where(p.heldout[..., None], rgb.detach(), p.image)
        photo = photo + ((rgb - target) ** 2).mean() + SSIM_WEIGHT * (1.0 - ssim_map(rgb, target).mean())
        held[k] = float(((rgb.detach() - p.image)[p.heldout] ** 2).mean())
    loss = photo
    terms = {"photo": float(photo.detach())}
    if cfg.use_mac and mac_sets:
        T = poses.cam_to_world().float()
        pix = {k: packs[k].pixel_map() for k in {s[0] for s in mac_sets} | {s[1] for s in mac_sets}}
        parts = [mac_loss(pix[a], pix[b], xa, xb, batch, w, T[a][None], T[b][None], cfg.mac,
                          check_inputs=False).loss for a, b, xa, xb, w, batch in mac_sets]  # fmt: skip
        mac = torch.stack(parts).mean()
        loss = loss + cfg.mac.weight * mac
        terms["mac"] = float(mac.detach())
    terms["loss"] = float(loss.detach())
    return loss, held, terms


def _schedule(n: int, per_step: int, steps: int) -> list[list[int]]:
    """The photos each step renders: ``per_step`` distinct ones of the ``n``, taken in turn from rounds that each
    visit every photo once in a fresh order (fixed seed). [steps][per_step]"""
    gen = torch.Generator().manual_seed(0)
    queue: list[int] = []
    out = []
    for _ in range(steps):
        if len(queue) < 2 * per_step:
            queue += torch.randperm(n, generator=gen).tolist()
        chosen: list[int] = []
        for k in list(queue):
            if len(chosen) < per_step and k not in chosen:
                chosen.append(k)
                queue.remove(k)
        out.append(sorted(chosen))
    return out


def _with_sh(maps: list[GaussianMaps], Ks: list[np.ndarray]) -> list[Packed]:
    """The maps' valid Gaussians as leaves to optimise (:class:`.packed.Packed`), their SH at :data:`SH_DEGREE` (the
    higher bands zero) and trainable only where :func:`~.sh_views.view_dependent` allows it (a gradient hook zeroes
    the rest: Adam then leaves them at 0)."""
    allowed = view_dependent(maps, Ks)
    k = (SH_DEGREE + 1) ** 2
    out = []
    for m, ok in zip(maps, allowed):
        sh = torch.nn.functional.pad(m.sh, (0, 0, 0, max(0, k - m.sh.shape[-2])))
        p = Packed.of(GaussianMaps(m.means, m.log_scales, m.quats, m.opacity_logits, sh.contiguous(), m.valid,
                                   m.cam_to_world))  # fmt: skip
        band = torch.ones(1, 1, len(p.idx), k, 1)
        band[..., 1:, :] = ok.reshape(-1)[p.idx].float()[None, None, :, None, None]
        p.leaves.sh.register_hook(lambda grad, band=band: grad * band)
        out.append(p)
    return out


def _stalled(heldout: list[float], step: int, patience: int, start: int) -> bool:
    """The held-out error has not fallen by :data:`HOLDOUT_TOL` of its best for ``patience`` steps, counted from step
    ``start``, the first whose curve holds every photo's error (before it the mean is over the photos rendered so
    far, another mean: on room 4 at full resolution and the pooled rates it rose by a quarter as the third photo
    came in, and the run stopped at :data:`MIN_STEPS`: mid / side 21.32 / 20.08 dB, 21.52 / 20.22 run to its end)."""
    curve = heldout[start - 1 :]
    if step < MIN_STEPS or len(curve) < patience + 1:
        return False
    best_before = min(curve[:-patience])
    return min(curve[-patience:]) > best_before * (1 - HOLDOUT_TOL)


def _frozen(m: GaussianMaps, cam_to_world: np.ndarray) -> GaussianMaps:
    """A refined map out of the graph, its camera the refined pose (the Gaussians ride with it)."""
    means, log_scales, quats, opacity_logits, sh = (x.detach() for x in m.tensors())
    return GaussianMaps(means, log_scales, quats, opacity_logits, sh, m.valid, torch.as_tensor(cam_to_world)[None])


def joint_refine(
    views: list[View], cam_to_world: list[np.ndarray], maps: list[GaussianMaps], config: RefineConfig, *,
    match_sets: list[MatchSet] | None = None, fixed: int = 0, on_step: RefineStep | None = None,
) -> JointResult:  # fmt: skip
    """Refine the Gaussians and the poses together (module docstring).

    Args:
        views: the cameras' photos (working resolution) and intrinsics ``K``; camera ``k`` is map ``k``'s photo.
        cam_to_world: each camera's pose as registered. [4, 4]
        maps: each photo's Gaussians (``B = 1``, its camera frame, ``cam_to_world`` its registered pose; not
            modified).
        config: the refinement's settings (``steps``: the most steps; ``scale``, losses, learning rates).
        match_sets: the verified matches of each matched pair (indices into ``maps``): the MAC loss's, and what
            decides which poses are already fixed (:func:`trusted_cameras`).
        fixed: the camera that does not move (the world frame's).
        on_step: called after each step with the step and its loss terms.
    """
    f = config.scale
    packs = _with_sh([m.pooled(f).detach() for m in maps], [v.K / np.array([[f], [f], [1]]) for v in views])
    params = [p.leaves for p in packs]
    photos = _photos(views, [v.K for v in views], cam_to_world, f)
    poses = _Poses(cam_to_world, fixed)
    trusted = trusted_cameras(list(match_sets or []), [v.K for v in views], cam_to_world, fixed, POSE_TRUST_PX * f)
    poses.free[torch.as_tensor(trusted)] = 0.0
    scene = _scene_depth(params)
    opt = _optimizer(params, config, scene, FULL_RESOLUTION_MEANS_RATE if f == 1 else 1.0)
    for lr, p in ((LR_ROTATION, poses.omega), (LR_CENTRE * scene, poses.delta)):
        opt.add_param_group({"params": [p], "lr": lr})
        opt.param_groups[-1]["initial_lr"] = lr
    # with every pose held, the MAC term only pulls matched Gaussians onto the match rays: -0.2 dB, 0.2 s a step
    use_mac = config.use_mac and bool(poses.free.any())
    mac_sets = _mac_sets(list(match_sets or []), [p.full for p in packs], f) if use_mac else []
    per_step = min(PHOTOS_PER_STEP, len(photos))
    where = centres(params)
    visible = [indices([True if m is not None and bool(m.all()) else m
                        for m in in_view(params, where, p.world_to_cam, p.K, p.image.shape[1], p.image.shape[0])])
               for p in photos]  # fmt: skip
    rounds = -(-len(photos) // per_step)  # the steps of a round: after the first, every photo's error is in
    patience = max(HOLDOUT_PATIENCE, rounds)  # a round at least: every photo's error updated
    schedule = _schedule(len(photos), per_step, config.steps)
    frames = frames_of(params)
    latest: dict[int, float] = {}  # each photo's held-out error when it was last rendered

    def step_loss(step: int) -> tuple[torch.Tensor, dict[str, float]]:
        loss, held, terms = _loss(params, poses, photos, schedule[step - 1], mac_sets, config, visible, packs, frames)
        latest.update(held)
        terms["heldout"] = float(np.mean(list(latest.values())))
        return loss, terms

    t0 = time.perf_counter()
    history, step, stopped = run_steps(
        opt, config, step_loss,
        lambda history, step: _stalled([h["heldout"] for h in history], step, patience, rounds), on_step,
    )  # fmt: skip
    with torch.no_grad():
        T = poses.cam_to_world()
        turned = torch.rad2deg(poses.omega.norm(dim=1) * poses.free[:, 0])
        T_np = [t.numpy().copy() for t in T]
        out = [_frozen(p.pixel_map(), T_np[k]) for k, p in enumerate(packs)]
    seconds = time.perf_counter() - t0
    logger.debug("joint refinement: %d steps in %.1f s, held-out %.5f → %.5f", step, seconds,
                 history[0]["heldout"], history[-1]["heldout"])  # fmt: skip
    free = [bool(x) for x in poses.free[:, 0] > 0]
    return JointResult(out, T_np, [float(a) for a in turned], step, seconds, stopped, history, free, bool(mac_sets))


def joint_reconstruction(
    rec: Reconstruction, config: RefineConfig, sets: list[MatchSet], on_step: RefineStep | None
) -> tuple[RefineResult, RefineReport]:
    """:func:`joint_refine` on a finished N-photo reconstruction (its registered photos, poses, maps and the matched
    pairs' MAC matches), camera 0 (the world frame) fixed, and the refinement's report section."""
    assert rec.poses is not None
    fixed = int(np.argmin([np.abs(T - np.eye(4)).max() for T in rec.poses]))
    config = dataclasses.replace(config, steps=math.ceil(config.steps * RENDERS_PER_STEP * len(rec.maps)))
    out = joint_refine(rec.views, rec.poses, rec.maps, config, match_sets=sets, fixed=fixed, on_step=on_step)
    result = RefineResult(out.maps, out.steps, out.seconds, out.stopped_early, out.history, poses=out.poses)
    report = RefineReport(steps=out.steps, max_steps=config.steps, stopped_early=out.stopped_early,
                          seconds=out.seconds, scale=config.scale, mac=out.mac, lpips=False,
                          loss_first=out.history[0], loss_last=out.history[-1], joint=out.report())  # fmt: skip
    return result, report
