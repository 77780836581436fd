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
PROBE_PHOTOS = 8
"""The photos :func:`sharp_gain_db` renders, spread over the registered ones (all of them up to this many): the
measure is a mean over photos, and rendering every photo from every other grew as photos² (2.0 s on 8 photos, ~35 s
projected at 32)."""
PROBE_NEIGHBOURS = 6
"""The other photos whose Gaussians predict a probed photo: those whose cameras are nearest to its camera (up to
seven photos, every other one, as the rule was chosen with). Room 8: +0.38 dB with every other photo, +0.32 with 6,
+0.18 with 2: the nearest photos agree sharp less clearly than the set (benchmarks/history/multiview_scaling.md)."""


def sharp_gain_db(maps: list[GaussianMaps], views: list[View], cam_to_world: list[np.ndarray], factor: int) -> float:
    """How much better the other photos' Gaussians predict a photo at full resolution than pooled ``factor × factor``
    (:meth:`~macsplat_cli.gaussians.GaussianMaps.pooled`): per probed photo ``k`` (:data:`PROBE_PHOTOS`), the PSNR of
    its :data:`PROBE_NEIGHBOURS` nearest photos' maps rendered into camera ``k`` (full resolution) against the photo,
    sharp minus pooled, on the pixels both renders cover (:data:`COVERED_ALPHA`); the mean over the probed photos, dB
    (NaN: no photo has such pixels).

    Args:
        maps: each registered photo's Gaussians (``B = 1``, ``cam_to_world`` set), photo ``k``'s map ``k``.
        views: the photos (working resolution) and their ``K``.
        cam_to_world: each photo's registered pose. [4, 4]
    """
    import torch

    from ..gaussians import Gaussians
    from ..render import render

    probes = _probes(cam_to_world)
    used = sorted({j for others in probes.values() for j in others})
    with torch.no_grad():  # each map's world Gaussians once, sharp and pooled
        scenes = [{j: maps[j].to_gaussians() for j in used}, {j: maps[j].pooled(factor).to_gaussians() for j in used}]
    gains = []
    for k, near in probes.items():
        v, T = views[k], cam_to_world[k]
        h, w = v.image.shape[:2]
        viewmat = torch.as_tensor(np.linalg.inv(T), dtype=torch.float32)
        K = torch.as_tensor(v.K, dtype=torch.float32)
        image = torch.as_tensor(v.image, dtype=torch.float32)
        errors, covered = [], torch.ones(h, w, dtype=torch.bool)
        for parts in scenes:
            others = Gaussians.cat([parts[j] for j in near])
            with torch.no_grad():
                out = render(others, viewmat, K, w, h)
            errors.append(((out.rgb.clamp(0, 1) - image) ** 2).mean(-1))
            covered &= out.alpha > COVERED_ALPHA
        if covered.any():
            sharp, blurred = (float(e[covered].mean()) for e in errors)
            gains.append(10 * math.log10(max(blurred, 1e-12) / max(sharp, 1e-12)))
    return float(np.mean(gains)) if gains else math.nan


def _probes(cam_to_world: list[np.ndarray]) -> dict[int, list[int]]:
    """The photos :func:`sharp_gain_db` renders (:data:`PROBE_PHOTOS`, evenly spread over the list), each with its
    :data:`PROBE_NEIGHBOURS` nearest other cameras (by centre, ties to the lower index)."""
    n = len(cam_to_world)
    centres = np.array([T[:3, 3] for T in cam_to_world])
    picked = sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, PROBE_PHOTOS))})
    out = {}
    for k in picked:
        d = np.linalg.norm(centres - centres[k], axis=1)
        d[k] = np.inf
        out[k] = sorted(np.argsort(d, kind="stable")[: min(PROBE_NEIGHBOURS, n - 1)].tolist())
    return out


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
