"""The compaction's entry points: :func:`compact` runs the steps in order and reports each one."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...cameras import Camera
from ...gaussians import GaussianMaps, Gaussians
from ...sh import num_sh_bases
from .blocks import adaptive
from .budget import keep_most_important
from .cleanup import prune_floaters, prune_occluded, prune_opacity, prune_subpixel
from .config import CompactConfig, CompactReport, CompactStep
from .dedup import dedup
from .sh_degree import sh_degree, sh_photo_check
from .state import ViewState, to_world, view_states

if TYPE_CHECKING:
    from ..run import Reconstruction

__all__ = ["compact", "compact_reconstruction"]

logger = logging.getLogger(__name__)


class _Steps:
    """The report's steps as they run: Gaussians alive before and after each, its time and its reason."""

    def __init__(self, views: list[ViewState]) -> None:
        self.views = views
        self.steps: list[CompactStep] = []

    def count(self) -> int:
        return sum(int(v.alive.sum()) for v in self.views)

    def run(self, name: str, fn: Callable[[], str]) -> None:
        """A step that marks pixels dead and returns its reason."""
        n0, t0 = self.count(), time.perf_counter()
        reason = fn()
        self.steps.append(CompactStep(name, n0, self.count(), time.perf_counter() - t0, reason))


def _prune_and_merge(views: list[ViewState], cfg: CompactConfig, steps: _Steps) -> list[Gaussians | None]:
    """Steps 1–6 on the views' pixels; returns each view's merged-block Gaussians (camera frame) or None."""
    steps.run("prune_opacity", lambda: prune_opacity(views))
    if cfg.prune_floaters:
        steps.run("prune_floaters", lambda: prune_floaters(views, cfg))
    if cfg.dedup and len(views) > 1:
        steps.run("dedup", lambda: dedup(views, cfg))
    if cfg.prune_occluded:
        steps.run("prune_occluded", lambda: prune_occluded(views, cfg))
    if cfg.subpixel_px > 0:
        steps.run("prune_subpixel", lambda: prune_subpixel(views, cfg))
    merged: list[Gaussians | None] = [None] * len(views)
    if cfg.adaptive:
        n0, t0 = steps.count(), time.perf_counter()
        reason, merged = adaptive(views, cfg)
        n1 = steps.count() + sum(len(g) for g in merged if g is not None)
        steps.steps.append(CompactStep("adaptive", n0, n1, time.perf_counter() - t0, reason))
    return merged


def _world_gaussians(views: list[ViewState], merged: list[Gaussians | None]) -> Gaussians:
    """The alive pixel Gaussians and the merged blocks of every view, in the world frame (view 0's first)."""
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
        parts.append(to_world(g, v.c2w))
    return Gaussians.cat(parts) if parts else Gaussians.empty()


def _reduce_sh(
    out: Gaussians, views: list[ViewState], cfg: CompactConfig, photos: bool, steps: list[CompactStep]
) -> Gaussians:
    """Step 7: the SH degree the views need (raised again where the photos ask for it, with ``sh="auto"``)."""
    t0 = time.perf_counter()
    deg, reason = sh_degree(out, views, cfg)
    if cfg.sh == "auto" and photos and deg < out.sh_degree:
        raised = sh_photo_check(views, out.sh_degree, deg, cfg)
        if raised is not None:
            deg, reason = raised
    if out.sh_degree > 0:
        steps.append(CompactStep("sh", len(out), len(out), time.perf_counter() - t0, reason))
        out = dataclasses.replace(out, sh=out.sh[:, : num_sh_bases(deg)].contiguous())
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
    views = view_states(maps, cameras, images)
    before = sum(int(v.alive.sum()) for v in views)
    sh_before = max((m.sh_degree for m in maps), default=0)
    steps = _Steps(views)
    with torch.no_grad():
        merged = _prune_and_merge(views, cfg, steps)
        out = _reduce_sh(_world_gaussians(views, merged), views, cfg, images is not None, steps.steps)
        if cfg.budget is not None and len(out) > cfg.budget:  # step 8
            t0 = time.perf_counter()
            n0 = len(out)
            out = keep_most_important(out, views, cfg.budget)
            why = "least important (opacity × largest projected area)"
            steps.steps.append(CompactStep("budget", n0, len(out), time.perf_counter() - t0, why))
    out = out.to(device)
    report = CompactReport(
        cfg.name, before, len(out), sh_before, out.sh_degree, time.perf_counter() - t_start, steps.steps
    )
    logger.debug("compaction: %s", report.summary())
    return out, report


def compact_reconstruction(rec: Reconstruction, config: CompactConfig | None = None) -> tuple[Gaussians, CompactReport]:
    """:func:`compact` on a finished (possibly refined) reconstruction: its maps, working-size cameras and photos."""
    cams = list(rec.cameras(original_size=False))
    return compact(rec.maps, cams, config, images=[v.image for v in rec.views])
