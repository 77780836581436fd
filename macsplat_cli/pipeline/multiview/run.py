"""The N-photo chain: duplicates out, pairs chosen, each pair's pose searched and accepted, the photos registered
in one frame, every registered photo's depth from its neighbours, and its Gaussians.

Returns a typed :class:`MultiViewResult`; :mod:`..run` turns it into the :class:`Reconstruction` and its report.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ...errors import ReconstructionError
from ...gaussians import GaussianMaps
from ..background import BackgroundConfig, BackgroundLayer, background_layer
from ..gaussian_init import GaussianInitConfig, view_gaussians
from ..pose import PoseSearch
from ..slots import StageTimer
from ..types import DepthMap, MatchSet, View
from .config import MultiViewConfig
from .covis import CovisReport, covisibility_init
from .depth import MIN_SHARED, DepthFn, multiview_depths, pair_geometry, photo_map
from .known import KNOWN_POSE_MAX_PX, known_pose_pairs, load_known_poses
from .pairwise import PairOutcome, cached_search, match_all
from .register import Registration, register_known, register_views
from .shortlist import global_descriptors, select_pairs, similarity
from .tracks import build_tracks

__all__ = ["MultiViewResult", "reconstruct_views"]

logger = logging.getLogger(__name__)


@dataclass
class MultiViewResult:
    """What the N-photo chain produced.

    Attributes:
        views: every input photo (self-calibrated ones replaced, with the registration's K).
        registration: poses, points, tracks, and why a photo is unregistered.
        pairs: every matched pair's outcome.
        depths: each photo's fused depth (None: unregistered or no depth pair).
        maps: each registered photo's Gaussians (world frame through ``cam_to_world``), in photo order.
        map_views: the photo of each map.
        depth_pairs: the pairs the depth ran on.
        duplicates: photo → the earlier photo it repeats.
    """

    views: list[View]
    registration: Registration
    pairs: list[PairOutcome]
    depths: list[DepthMap | None]
    maps: list[GaussianMaps]
    map_views: list[int]
    depth_pairs: list[tuple[int, int]]
    duplicates: dict[int, int]
    scale: Literal["relative", "metric"] | None = None
    """The given poses' scale (``--poses``), else None (relative: the first pair's baseline is 1)."""
    background: BackgroundLayer | None = None
    """The far layer around every registered photo (:mod:`..background`), when built."""
    covisibility: CovisReport | None = None
    """What the co-visibility initialisation kept (:mod:`.covis`), when it ran."""

    def unregistered(self) -> list[dict[str, Any]]:
        """The photos left out: name, original size and why (the cameras file lists them)."""
        reg = self.registration
        return [{"name": v.name, "registered": False, "width": v.original_size[0], "height": v.original_size[1],
                 "reason": reg.reasons[k] or "no depth could be estimated for it"}
                for k, v in enumerate(self.views) if k not in self.map_views]  # fmt: skip

    def match_sets(self) -> list[MatchSet]:
        """The refinement's MAC matches: for every accepted pair of photos that both have Gaussians, their shared
        tracks (indices into ``maps``)."""
        index = {k: i for i, k in enumerate(self.map_views)}
        out = []
        for o in self.pairs:
            if o.result is not None and o.i in index and o.j in index:
                m = pair_geometry(self.registration, o.i, o.j)[0].inliers
                out.append(MatchSet(index[o.i], index[o.j], m.xy0, m.xy1, np.ones(len(m), np.float32)))
        return out

    def report(self) -> dict[str, Any]:
        """The report's ``multiview`` section: per photo, per pair, the registration."""
        reg = self.registration
        per = reg.per_view()
        photos = []
        for k, v in enumerate(self.views):
            entry: dict[str, Any] = {"name": v.name, "registered": bool(reg.registered[k] and k in self.map_views),
                                     "intrinsics_source": v.intrinsics_source, "focal_px_working": float(v.K[0, 0]),
                                     **per[k]}  # fmt: skip
            if not entry["registered"]:
                entry["reason"] = reg.reasons[k] or "no depth could be estimated for it"
            photos.append(entry)
        names = [v.name for v in self.views]
        pairs = [{"photos": [names[o.i], names[o.j]], "accepted": o.result is not None, "inliers": o.inliers,
                  "seconds": round(o.seconds, 3), **({"reason": o.reason} if o.reason else {})}
                 for o in self.pairs]  # fmt: skip
        ok = reg.point_ok[reg.tracks.track]
        r = reg.residual_px[ok & reg.registered[reg.tracks.view]]
        return {
            "photos": photos,
            "registered": int(sum(p["registered"] for p in photos)),
            "pairs": pairs,
            "init_pair": [names[k] for k in reg.init_pair] if min(reg.init_pair) >= 0 else None,
            "registration_order": [names[k] for k in reg.order],
            "points": int(reg.point_ok.sum()),
            "reprojection_rms_px": float(np.sqrt(np.mean(r**2))) if len(r) else None,
            "depth_pairs": [[names[a], names[b]] for a, b in self.depth_pairs],
            "duplicates": {names[k]: names[f] for k, f in self.duplicates.items()},
            **({"covisibility": self.covisibility.to_dict()} if self.covisibility is not None else {}),
        }


def _duplicates(views: Sequence[View]) -> dict[int, int]:
    """Photo → the earlier photo it repeats (the same file, or identical pixels at the working size)."""
    seen: dict[str, int] = {}
    out = {}
    for k, v in enumerate(views):
        key = hashlib.sha1(np.ascontiguousarray(v.image).tobytes()).hexdigest()
        try:
            key_path = str(v.path.resolve())
        except OSError:
            key_path = str(v.path)
        first = seen.get(key, seen.get(key_path))
        if first is not None:
            out[k] = first
            continue
        seen[key] = seen[key_path] = k
    return out


def reconstruct_views(
    views: list[View], search: PoseSearch, two_view_depth: DepthFn, gaussians: GaussianInitConfig,
    background: BackgroundConfig, config: MultiViewConfig, timed: StageTimer,
) -> MultiViewResult:  # fmt: skip
    """The chain (module docstring) on ``views`` (≥ 3 photos, or ≥ 2 with ``config.poses``), already loaded.

    Raises:
        ReconstructionError: fewer than two photos could be registered (the reasons are in the message).
    """
    dups = _duplicates(views)
    for k, first in dups.items():
        logger.warning("%s repeats %s: left out", views[k].name, views[first].name)
    live = [k for k in range(len(views)) if k not in dups]
    cached = cached_search(search, accept_low_confidence=True)
    sub = [views[k] for k in live]
    known = load_known_poses(config.poses, views) if config.poses is not None else None

    def pairs_stage() -> list[PairOutcome]:
        # every photo's descriptors at once, side by side (per pair, most pairs would describe one new photo alone)
        feats = cached.describe(sub, None)
        # the VLADs once, if retrieval or the slow tiers' order needs them
        vlads = functools.cache(lambda: global_descriptors(feats, config.shortlist))
        chosen = select_pairs(len(sub), feats, config.shortlist, vlads)
        if known is not None:
            full = [(live[i], live[j]) for i, j in chosen]
            return known_pose_pairs(views, full, cached.describe, cached.match, known, KNOWN_POSE_MAX_PX)
        outs = match_all(sub, chosen, cached, lambda: similarity(feats, config.shortlist, vlads))
        return [dataclasses.replace(o, i=live[o.i], j=live[o.j]) for o in outs]

    outcomes: list[PairOutcome] = timed("pairs", pairs_stage)

    def register_stage() -> Registration:
        tracks = build_tracks(outcomes)
        if known is None:
            return register_views(views, outcomes, tracks)
        reg = register_known(views, tracks, known.R, known.t)
        reg.registered[list(dups)] = False
        return reg

    reg = timed("register", register_stage)
    for k, first in dups.items():
        reg.reasons[k] = f"the same photo as {views[first].name}"
    if int(reg.registered.sum()) < 2:
        raise ReconstructionError(_refusal(views, reg, outcomes, len(live)))
    views = [_calibrated(v, reg, k) for k, v in enumerate(views)]
    depths, dpairs = timed("depth", lambda: multiview_depths(views, reg, two_view_depth))
    if not dpairs:
        raise ReconstructionError(
            f"no two registered photos share {MIN_SHARED} triangulated points: no depth can be estimated"
        )

    def gaussian_stage() -> tuple[list[GaussianMaps], list[int], BackgroundLayer | None, CovisReport | None]:
        kept = [(k, d) for k, d in enumerate(depths) if d is not None]
        ks = [k for k, _ in kept]
        Ts = [reg.cam_to_world(k) for k in ks]

        def one(job: tuple[tuple[int, DepthMap], np.ndarray]) -> GaussianMaps:
            (k, d), T = job
            return view_gaussians(views[k], d, reg.K[k], T, gaussians)

        maps = photo_map(one, zip(kept, Ts))  # NumPy releases the GIL: the photos side by side
        covis = None
        if config.covisibility:
            maps, covis = covisibility_init(maps, [reg.K[k] for k in ks])
        layer = None
        if background.enabled:
            layer = background_layer([views[k] for k in ks], [reg.K[k] for k in ks], Ts, [d for _, d in kept],
                                     background)  # fmt: skip
        return maps, ks, layer, covis

    maps, ks, layer, covis = timed("gaussians", gaussian_stage)
    scale: Literal["metric"] | None = "metric" if known is not None and known.scale == "metric" else None
    return MultiViewResult(views, reg, outcomes, depths, maps, ks, dpairs, dups, scale, layer, covis)


def _calibrated(v: View, reg: Registration, k: int) -> View:
    if reg.focal_estimated[k] and reg.registered[k]:
        return dataclasses.replace(v, K=reg.K[k].copy(), intrinsics_source="estimated")
    return v


def _refusal(views: Sequence[View], reg: Registration, outcomes: Sequence[PairOutcome], distinct: int) -> str:
    n_ok = sum(o.result is not None for o in outcomes)
    first = next((o.reason for o in outcomes if o.reason), None)
    if distinct < 2:
        why = f"the {len(views)} photos are all the same photo"
    elif n_ok == 0:
        why = f"no pair of the {len(views)} photos gave an accepted pose"
        why += f" (first refusal: {first})" if first else ""
    else:
        why = f"only {int(reg.registered.sum())} of {len(views)} photos could be registered"
    return f"{why}; at least two registered photos are needed"
