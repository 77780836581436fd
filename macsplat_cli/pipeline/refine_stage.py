"""Stage 7's entry: the refinement a reconstruction takes (``--refine``, ``--quality best``).

Two photos: the per-view maps on both photos with the MAC loss, the cameras fixed (:mod:`.refine`). More photos
(registered, no LPIPS term): the Gaussians and the poses together over every photo (:mod:`.multiview.joint`).

Where the preset left the refinement's resolution to the photos (``RefineConfig.coarse``: ``best`` on three photos
or more), the photos decide it first (:func:`sharp_gain_db`; the rule is
:func:`~macsplat_cli.presets.refine_for_agreement`'s): each registered photo is rendered from the other photos'
Gaussians at full resolution and pooled ``2 × 2``; where the sharp Gaussians agree less than the pooled ones with the
photos they did not come from (registered cameras a few tenths of a degree off), refining and writing them at full
resolution loses on views no photo took (benchmarks/history/multiview_joint.md).
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

from ..report import RefineReport
from .refine import RefineConfig, RefineResult, RefineStep, check_scale, refine_reconstruction

if TYPE_CHECKING:
    import torch

    from ..gaussians import GaussianMaps
    from .run import Reconstruction
    from .types import View

__all__ = ["check_scale", "refine_stage", "sharp_gain_db"]

COVERED_ALPHA = 0.95
"""A photo's pixel counts in :func:`sharp_gain_db` where both renders of the other photos' Gaussians cover it this
much (the pixels only the photo itself sees say nothing of how its neighbours agree with it)."""


def sharp_gain_db(maps: list[GaussianMaps], views: list[View], cam_to_world: list[np.ndarray], factor: int) -> float:
    """How much better the other photos' Gaussians predict each photo at full resolution than pooled
    ``factor × factor`` (:meth:`~macsplat_cli.gaussians.GaussianMaps.pooled`): per photo ``k``, the PSNR of the
    other maps rendered into camera ``k`` (full resolution) against the photo, sharp minus pooled, on the pixels both
    renders cover (:data:`COVERED_ALPHA`); the mean over the photos, dB (NaN: no photo has such pixels).

    Args:
        maps: each registered photo's Gaussians (``B = 1``, ``cam_to_world`` set), photo ``k``'s map ``k``.
        views: the photos (working resolution) and their ``K``.
        cam_to_world: each photo's registered pose. [4, 4]
    """
    import torch

    from ..gaussians import Gaussians
    from ..render import render

    with torch.no_grad():  # each map's world Gaussians once, sharp and pooled
        scenes = [[m.to_gaussians() for m in maps], [m.pooled(factor).to_gaussians() for m in maps]]
    gains = []
    for k, (v, T) in enumerate(zip(views, cam_to_world)):
        h, w = v.image.shape[:2]
        viewmat = torch.as_tensor(np.linalg.inv(T), dtype=torch.float32)
        K = torch.as_tensor(v.K, dtype=torch.float32)
        image = torch.as_tensor(v.image, dtype=torch.float32)
        errors, covered = [], torch.ones(h, w, dtype=torch.bool)
        for parts in scenes:
            others = Gaussians.cat([g for j, g in enumerate(parts) if j != k])
            with torch.no_grad():
                out = render(others, viewmat, K, w, h)
            errors.append(((out.rgb.clamp(0, 1) - image) ** 2).mean(-1))
            covered &= out.alpha > COVERED_ALPHA
        if covered.any():
            sharp, blurred = (float(e[covered].mean()) for e in errors)
            gains.append(10 * math.log10(max(blurred, 1e-12) / max(sharp, 1e-12)))
    return float(np.mean(gains)) if gains else math.nan


def refine_stage(
    rec: Reconstruction, config: RefineConfig, *, lpips: torch.nn.Module | None = None,
    on_step: RefineStep | None = None,
) -> tuple[RefineResult, RefineReport]:  # fmt: skip
    """The refinement of ``rec`` (module docstring) and its report section; ``RefineResult.poses`` is set when the
    poses were refined.

    Raises:
        InputError: the working size is not divisible by ``config.scale`` (:func:`check_scale`); a size the
            ``coarse`` scale does not divide keeps ``config.scale`` unmeasured.
    """
    if rec.multiview is None or rec.poses is None or lpips is not None:
        return refine_reconstruction(rec, config, lpips=lpips, on_step=on_step)
    from ..presets import refine_for_agreement
    from .multiview.joint import joint_reconstruction

    gain = None
    f = config.coarse[0] if config.coarse is not None else 0
    if f and len(rec.maps) > 1 and not any(m.size[0] % f or m.size[1] % f for m in rec.maps):  # else: not pooled
        gain = sharp_gain_db(rec.maps, rec.views, rec.poses, f)
        config = refine_for_agreement(config, gain)
    check_scale(rec.maps, config.scale)
    result, report = joint_reconstruction(rec, config, rec.multiview.match_sets(), on_step)
    if gain is not None and report.joint is not None:
        report = dataclasses.replace(report, joint={**report.joint, "sharp_gain_db": round(gain, 3)})
    return result, report
