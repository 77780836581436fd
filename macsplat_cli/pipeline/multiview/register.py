"""Global poses by incremental registration: the best pair, triangulation, PnP with RANSAC for the next photo,
triangulation, bundle adjustment, until no photo is left that the points can register.

Own code rather than pycolmap's mapper: the pairs' geometry has already been through macsplat's acceptance, the
photos' intrinsics and keypoints are macsplat's, and a few dozen photos need neither COLMAP's database nor its
rig model; ``scipy.optimize.least_squares`` with a sparse Jacobian is the bundle adjustment
(:mod:`.bundle`). A photo is registered only when its PnP pose has enough inliers *and* agrees with every accepted
pair it has with a registered photo: a pose two views accepted is never contradicted silently.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from ...metrics import rotation_error_deg
from ..types import View
from .bundle import BundleConfig, bundle_adjust
from .pairwise import PairOutcome
from .resection import anchored_pose, pair_anchor, pnp_pose
from .tracks import Tracks
from .triangulate import project, triangulate_tracks

__all__ = ["Registration", "register_known", "register_views"]

logger = logging.getLogger(__name__)


INIT_MIN_PARALLAX_DEG = 2.0
"""The first pair needs this median parallax (°): less, and its triangulation is too uncertain to register the
others on (a pair below it still starts when no other pair has it)."""
MIN_PNP_INLIERS = 30
"""PnP inliers a photo needs (the two-view support minimum's order of magnitude)."""
MIN_PNP_SHARE = 0.2
"""...and this share of its 2D–3D correspondences (a random pose explains few; the correspondences chained through
epipolar-guided matches are often three-quarters wrong on wide real pairs)."""
MIN_ANCHOR_INLIERS = 15
"""A pose anchored on an accepted pair (one free parameter, the baseline's length) needs this many points it
reprojects within :data:`PNP_ERROR_PX`."""
PNP_ERROR_PX = 3.0
"""PnP's RANSAC threshold (px at the working size: the matches' noise is ~1 px)."""
MAX_PAIR_DISAGREEMENT_DEG = 5.0
"""A registered pose's rotation relative to each registered photo it has an accepted pair with must agree with that
pair's within this (°): the two-view poses are accurate to ~1°."""
MAX_ERROR_PX = 4.0
"""An observation farther than this (px) from its point's projection after the bundle adjustment is an outlier
(dropped), and a triangulated point needs all its observations within it."""
MIN_ANGLE_DEG = 1.5
"""A point is triangulated when its rays span at least this angle (°)."""
FOCAL_SCAN = (1.0,)
"""An unknown shared focal's starts, as factors of the pairs' estimate (or the prior's); the registration whose
truncated reprojection cost is lowest is kept. One start: the adjustment converges from far-off starts on the tests'
object orbit (tests/pipeline/multiview/test_multiview.py)."""
BUNDLE_GROWTH = 1.5
"""The whole registration is adjusted each time the registered photos have grown by this factor (and at the end): the
adjustments' total size stays within 1 / (1 − 1/1.5) = 3× the last one's. At 32 photos of the scaling orbit 1.2 and
1.5 end with the same poses (mean rotation error 0.035°) and 1.5 takes 35 % less time (multiview_scaling.md)."""
BUNDLE = BundleConfig(ftol=1e-4)
"""The registration's bundle adjustment: cost tolerance 1e-4 (not 1e-6), the poses end within 0.01° of the fully
converged ones (far below the matches' noise) in a third of the evaluations."""


@dataclass
class Registration:
    """Every photo's pose in one frame (world = the first registered photo's camera; unit: the first pair's
    baseline), or why it has none.

    Attributes:
        R, t: world → camera (``X_cam = R X + t``); NaN where unregistered. [N, 3, 3], [N, 3]
        K: intrinsics at the working size (self-calibrated where the focal was estimated). [N, 3, 3]
        registered: [N] bool
        reasons: why each unregistered photo is not (None where registered).
        points: the tracks' 3D points (world). [P, 3]; ``point_ok`` [P] bool: triangulated and kept.
        tracks: the observations (outliers removed).
        residual_px: each observation's reprojection error after the last adjustment. [O]
        init_pair: the pair registration started from.
        order: the photos in the order they were registered.
        focal_estimated: [N] bool, the bundle adjustment estimated the photo's focal.
    """

    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    registered: np.ndarray
    reasons: list[str | None]
    points: np.ndarray
    point_ok: np.ndarray
    tracks: Tracks
    residual_px: np.ndarray
    init_pair: tuple[int, int]
    order: list[int]
    focal_estimated: np.ndarray

    def cam_to_world(self, k: int) -> np.ndarray:
        """Camera-to-world of photo ``k`` (registered). [4, 4]"""
        T = np.eye(4)
        T[:3, :3] = self.R[k].T
        T[:3, 3] = -self.R[k].T @ self.t[k]
        return T

    def per_view(self) -> list[dict[str, float | int]]:
        """Each photo's observations and reprojection RMS (px), for the report."""
        out = []
        for k in range(len(self.registered)):
            sel = (self.tracks.view == k) & self.point_ok[self.tracks.track]
            r = self.residual_px[sel]
            out.append({"observations": int(sel.sum()),
                        "reprojection_rms_px": float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")})  # fmt: skip
        return out


class _State:
    """The registration in progress."""

    def __init__(self, views: Sequence[View], tracks: Tracks) -> None:
        n = len(views)
        self.views, self.tracks = views, tracks
        self.R = np.full((n, 3, 3), np.nan)
        self.t = np.full((n, 3), np.nan)
        self.K = np.stack([v.K for v in views]).astype(np.float64)
        self.registered = np.zeros(n, bool)
        self.order: list[int] = []
        self.points = np.zeros((tracks.n_tracks, 3))
        self.point_ok = np.zeros(tracks.n_tracks, bool)
        self.inlier = np.ones(len(tracks), bool)  # observations not (yet) found to be outliers
        self.residual = np.full(len(tracks), np.nan)
        self.focal_group = np.full(n, -1)

    def add(self, k: int, R: np.ndarray, t: np.ndarray) -> None:
        self.R[k], self.t[k] = R, t
        self.registered[k] = True
        self.order.append(k)

    def _obs(self) -> np.ndarray:
        return self.inlier & self.registered[self.tracks.view]

    def triangulate(self) -> None:
        """Every track with ≥ 2 registered observations, from all of them (points already kept stay kept when
        their new estimate fails: the bundle adjustment moves them). Only the tracks not kept yet are solved (a
        track's solution depends on its own observations and the cameras only): the work follows the new tracks."""
        sel = self._obs()
        tr = self.tracks
        n_obs = np.bincount(tr.track[sel], minlength=tr.n_tracks)
        pending = ~self.point_ok & (n_obs >= 2)
        sel &= pending[tr.track]
        ids = np.flatnonzero(pending)
        if len(ids) == 0:
            return self._reject()
        compact = np.full(tr.n_tracks, -1)
        compact[ids] = np.arange(len(ids))
        cams = np.flatnonzero(self.registered)
        index = np.full(len(self.registered), -1)
        index[cams] = np.arange(len(cams))
        tri = triangulate_tracks(self.R[cams], self.t[cams], self.K[cams], index[tr.view[sel]],
                                 compact[tr.track[sel]], tr.xy[sel], len(ids), max_error_px=MAX_ERROR_PX,
                                 min_angle_deg=MIN_ANGLE_DEG)  # fmt: skip
        new = ids[tri.ok]
        self.points[new] = tri.points[tri.ok]
        self.point_ok[new] = True
        self._reject()

    def _errors(self, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reprojection error (px) and camera depth of the observations ``sel`` (indices). [len(sel)] each"""
        tr = self.tracks
        pix, z = project(self.R, self.t, self.K, tr.view[sel], self.points[tr.track[sel]])
        return np.linalg.norm(pix - tr.xy[sel], axis=1), z

    def _kept(self) -> np.ndarray:
        """The observations of kept points in registered photos (indices)."""
        return np.flatnonzero(self._obs() & self.point_ok[self.tracks.track])

    def measure(self) -> None:
        """Every kept observation's reprojection error (``residual``), for the report."""
        sel = self._kept()
        self.residual[sel] = self._errors(sel)[0]

    def _reject(self) -> None:
        """Observations farther than ``max_error_px`` from their kept point's projection leave their track (a new
        photo's keypoint that a wrong match chained to an old point), before they reach the adjustment."""
        sel = self._kept()
        e, z = self._errors(sel)
        self.inlier[sel[~(e <= MAX_ERROR_PX) | (z <= 0)]] = False
        alive = np.bincount(self.tracks.track[self._obs()], minlength=self.tracks.n_tracks)
        self.point_ok &= alive >= 2

    def adjust(self) -> float:
        """Bundle adjustment of the registered photos and kept points; outlier observations dropped. RMS (px)."""
        cams = np.array(self.order)
        index = np.full(len(self.registered), -1)
        index[cams] = np.arange(len(cams))
        tr = self.tracks
        sel = self._obs() & self.point_ok[tr.track]
        pts = np.flatnonzero(self.point_ok)
        pindex = np.full(tr.n_tracks, -1)
        pindex[pts] = np.arange(len(pts))
        fixed = np.zeros(len(cams), bool)
        fixed[0] = True
        groups = self.focal_group[cams] if len(cams) >= 3 else np.full(len(cams), -1)
        with threadpool_limits(1, user_api="blas"):  # small products (3 × 3 per point): one BLAS thread is fastest
            res = bundle_adjust(self.R[cams], self.t[cams], self.K[cams], self.points[pts], index[tr.view[sel]],
                                pindex[tr.track[sel]], tr.xy[sel], fixed_pose=fixed, focal_group=groups,
                                config=BUNDLE)  # fmt: skip
        self.R[cams], self.t[cams], self.K[cams], self.points[pts] = res.R, res.t, res.K, res.points
        for g in np.unique(groups[groups >= 0]):  # a shared focal: the photos not yet registered start from it
            members = np.flatnonzero(self.focal_group == g).tolist()
            f = res.K[int(np.flatnonzero(groups == g)[0]), 0, 0] / self.views[int(cams[groups == g][0])].K[0, 0]
            for m in members:
                self.K[m, :2, :2] = self.views[m].K[:2, :2] * f
        self.residual[sel] = res.residual_px
        bad = np.flatnonzero(sel)[res.residual_px > MAX_ERROR_PX]
        self.inlier[bad] = False
        # a point left with < 2 observations is no longer kept
        alive = np.bincount(tr.track[self._obs()], minlength=tr.n_tracks)
        self.point_ok &= alive >= 2
        return res.rms_after_px

    def truncated_cost(self, cap_px: float = 2.0) -> float:
        """Mean of min(e, cap)² over every observation of a kept point in a registered photo, outliers included: a
        wrong focal is seen in the errors the adjustment dropped, not only in those it kept."""
        sel = np.flatnonzero(self.registered[self.tracks.view] & self.point_ok[self.tracks.track])
        if not sel.size:
            return float("inf")
        e, z = self._errors(sel)
        return float(np.mean(np.minimum(np.where(z > 0, e, cap_px), cap_px) ** 2))

    def correspondences(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Photo ``k``'s observations of kept points: (points [M, 3], pixels [M, 2])."""
        tr = self.tracks
        sel = (tr.view == k) & self.inlier & self.point_ok[tr.track]
        return self.points[tr.track[sel]], tr.xy[sel]


def _init_pair(outcomes: Sequence[PairOutcome]) -> PairOutcome | None:
    """The accepted pair to start from: among those that close a consistent loop of three (when any does; else
    all), those with enough parallax (else all), the one with the most verified matches."""
    ok = [o for o in outcomes if o.result is not None and not o.provisional]
    ok = ok or [o for o in outcomes if o.result is not None]
    if not ok:
        return None
    ok = _in_consistent_loops(ok, MAX_PAIR_DISAGREEMENT_DEG) or ok
    wide = [o for o in ok if (o.geometry.median_parallax_deg or 0.0) >= INIT_MIN_PARALLAX_DEG]
    return max(wide or ok, key=lambda o: (o.inliers, -o.i, -o.j))


def _in_consistent_loops(pairs: Sequence[PairOutcome], max_deg: float) -> list[PairOutcome]:
    """The pairs on a loop of three photos whose relative rotations compose to within ``max_deg`` of the identity:
    a wrong pose that two views accepted rarely closes a loop with two right ones (ICL: one 14.6° off, 596 matches,
    the most of its set)."""
    R = {(o.i, o.j): o.geometry.R for o in pairs}

    def rel(a: int, b: int) -> np.ndarray | None:
        return R[(a, b)] if (a, b) in R else R[(b, a)].T if (b, a) in R else None

    keep: set[tuple[int, int]] = set()
    photos = sorted({k for o in pairs for k in (o.i, o.j)})
    for i, j in R:
        for k in photos:
            jk, ik = rel(j, k), rel(i, k)
            if k in (i, j) or jk is None or ik is None:
                continue
            # i → j → k against i → k
            if rotation_error_deg(jk @ R[(i, j)], ik) <= max_deg:
                keep |= {(i, j), (min(j, k), max(j, k)), (min(i, k), max(i, k))}
    return [o for o in pairs if (o.i, o.j) in keep]


def _disagreement(st: _State, k: int, R: np.ndarray, outcomes: Sequence[PairOutcome]) -> tuple[float, str | None]:
    """The largest disagreement (°) of photo ``k``'s rotation with its accepted pairs to registered photos."""
    worst, name = 0.0, None
    for o in outcomes:
        if o.result is None or o.provisional or k not in (o.i, o.j):
            continue
        other = o.j if o.i == k else o.i
        if not st.registered[other]:
            continue
        Ri, Rj = (R, st.R[other]) if o.i == k else (st.R[other], R)
        e = rotation_error_deg(Rj @ Ri.T, o.result.geometry.R)
        if e > worst:
            worst, name = e, st.views[other].name
    return worst, name


def _unknown_focal(views: Sequence[View], outcomes: Sequence[PairOutcome]) -> tuple[np.ndarray, np.ndarray]:
    """The starting K of each photo whose focal is only the prior's (the median of its pairs' self-calibrated
    focal lengths, else the prior), and the focal groups: photos of one size with an unknown focal share one."""
    K = np.stack([v.K for v in views]).astype(np.float64)
    groups = np.full(len(views), -1)
    sizes: dict[tuple[int, int], int] = {}
    for k, v in enumerate(views):
        if v.intrinsics_source != "prior":
            continue
        groups[k] = sizes.setdefault(v.original_size, len(sizes))
        fs = [o.result.views[0 if o.i == k else 1].K[0, 0] / v.K[0, 0] for o in outcomes
              if o.result is not None and k in (o.i, o.j) and o.result.geometry.focal_estimated]  # fmt: skip
        if fs:
            K[k, :2, :2] *= float(np.median(fs))
    # one shared focal per group: the group's median start
    for g in range(len(sizes)):
        members = np.flatnonzero(groups == g).tolist()
        scale = np.median([K[m, 0, 0] / views[m].K[0, 0] for m in members])
        for m in members:
            K[m, :2, :2] = views[m].K[:2, :2] * scale
    return K, groups


def register_views(views: Sequence[View], outcomes: Sequence[PairOutcome], tracks: Tracks) -> Registration:
    """Incremental registration of ``views`` (module docstring). Photos with an unknown focal share one per image
    size; with ≥ 3 photos it is scanned (:data:`FOCAL_SCAN`: the registration at each start, the one
    whose reprojection errors, truncated, are smallest) and then refined by the bundle adjustment — which alone
    stays in the basin of a far-off start.

    Returns:
        The :class:`Registration`; photos that could not be registered carry their reason. With no accepted pair
        nothing is registered (the caller refuses the scene).
    """
    K0, groups = _unknown_focal(views, outcomes)
    first = _init_pair(outcomes)
    if first is None:
        st = _State(views, tracks)
        return _finish(st, ["no pair with this photo gave an accepted pose"] * len(views), (-1, -1))
    scales = FOCAL_SCAN if (groups >= 0).any() and len(views) >= 3 else (1.0,)
    best: tuple[tuple[int, float], _State, list[str | None]] | None = None
    for s in scales:
        K = K0.copy()
        K[groups >= 0, :2, :2] *= s
        st, reasons = _incremental(views, outcomes, tracks, first, K, groups)
        score = (-int(st.registered.sum()), st.truncated_cost())
        logger.debug("focal start ×%.2f: %d registered, truncated cost %.3f", s, -score[0], score[1])
        if best is None or score < best[0]:
            best = (score, st, reasons)
    assert best is not None
    return _finish(best[1], best[2], (first.i, first.j))


def _incremental(
    views: Sequence[View], outcomes: Sequence[PairOutcome], tracks: Tracks, first: PairOutcome,
    K: np.ndarray, groups: np.ndarray,
) -> tuple[_State, list[str | None]]:  # fmt: skip
    """One incremental registration from ``first`` with the starting intrinsics ``K`` [N, 3, 3]."""
    st = _State(views, tracks)
    st.K, st.focal_group = K, groups
    if groups[first.i] < 0 and groups[first.j] < 0:
        g = first.geometry
        st.K[first.i], st.K[first.j] = g.K0, g.K1
        R, t = g.R, g.t
    else:  # the pair's pose at these intrinsics
        R, t = _pose_at(first, st.K[first.i], st.K[first.j], PNP_ERROR_PX)
    st.add(first.i, np.eye(3), np.zeros(3))
    st.add(first.j, R, t)
    st.triangulate()
    if st.point_ok.any():
        st.adjust()
    adjusted = len(st.order)
    failed: dict[int, str] = {}
    while True:
        k, why = _register_next(st, outcomes, failed)
        if k is None:
            break
        if why is not None:
            failed[k] = why
            continue
        failed.clear()  # more points: the photos that failed may register now
        st.triangulate()
        if len(st.order) >= BUNDLE_GROWTH * adjusted:  # the whole set, each time it has grown by a fifth
            st.adjust()
            st.triangulate()
            adjusted = len(st.order)
    if adjusted < len(st.order):
        st.adjust()
        st.triangulate()
    st.measure()
    reasons: list[str | None] = [None] * len(views)
    for k in range(len(views)):
        if not st.registered[k]:
            reasons[k] = failed.get(k) or _unpaired_reason(k, outcomes)
    return st, reasons


def _pose_at(o: PairOutcome, K0: np.ndarray, K1: np.ndarray, threshold_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The pair's relative pose from its verified matches at the intrinsics ``K0``, ``K1`` (RANSAC on the essential
    matrix in normalised coordinates, then the cheirality test)."""
    m = o.geometry.inliers
    n0 = cv2.undistortPoints(m.xy0[:, None], K0, None)[:, 0]
    n1 = cv2.undistortPoints(m.xy1[:, None], K1, None)[:, 0]
    f = 0.5 * (K0[0, 0] + K1[0, 0])
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=threshold_px / f)
    if E is None:
        g = o.geometry
        return g.R, g.t
    _, R, t, _ = cv2.recoverPose(E[:3], n0, n1, np.eye(3), mask=mask)
    return R, t[:, 0] / max(float(np.linalg.norm(t)), 1e-12)


def _pair_K(st: _State, o: PairOutcome) -> tuple[np.ndarray, np.ndarray]:
    """The first pair's intrinsics: the shared focal's start for photos with an unknown focal, else their own."""
    g = o.geometry
    return (st.K[o.i] if st.focal_group[o.i] >= 0 else g.K0), (st.K[o.j] if st.focal_group[o.j] >= 0 else g.K1)


def _unpaired_reason(k: int, outcomes: Sequence[PairOutcome]) -> str:
    mine = [o for o in outcomes if k in (o.i, o.j)]
    if not mine:
        return "not paired with any photo"
    if all(o.result is None for o in mine):
        return f"no accepted pose with any other photo ({mine[0].reason})"
    return "too few of its matches reach points the registered photos triangulated"


def _register_next(
    st: _State, outcomes: Sequence[PairOutcome], failed: dict[int, str]
) -> tuple[int | None, str | None]:
    """Registers the unregistered photo with the most correspondences (PnP, else anchored on an accepted pair:
    :mod:`.resection`): (photo, None) when registered, (photo, reason) when it failed, (None, None) when no photo
    is left to try."""
    tr = st.tracks
    sel = st.inlier & st.point_ok[tr.track]
    counts = np.bincount(tr.view[sel], minlength=len(st.views))
    counts[st.registered] = -1
    for k in failed:
        counts[k] = -1
    k = int(np.argmax(counts))
    if counts[k] < min(MIN_PNP_INLIERS, MIN_ANCHOR_INLIERS):
        return None, None
    obj, xy = st.correspondences(k)
    n, thr = len(obj), PNP_ERROR_PX
    found = pnp_pose(obj, xy, st.K[k], thr) if n >= MIN_PNP_INLIERS else None
    how = "PnP"
    if found is None or found[2] < MIN_PNP_INLIERS or found[2] < MIN_PNP_SHARE * n:
        found, how = _anchored(st, k, obj, xy, outcomes), "anchored on an accepted pair"
        if found is None:
            return k, f"neither PnP nor its accepted pairs explain its {n} matches to triangulated points"
    R, t, n_in = found
    worst, other = _disagreement(st, k, R, outcomes)
    if worst > MAX_PAIR_DISAGREEMENT_DEG:
        return k, f"its pose disagrees by {worst:.1f}° with its accepted pose relative to {other}"
    st.add(k, R, t)
    logger.debug("registered %s (%s): %d of %d inliers", st.views[k].name, how, n_in, n)
    return k, None


def _anchored(
    st: _State, k: int, obj: np.ndarray, xy: np.ndarray, outcomes: Sequence[PairOutcome]
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Photo ``k``'s pose from its best-supported accepted pair with a registered photo (the pair's rotation and
    translation direction — re-estimated at the current focal for a provisional pair —, the length from the points),
    when it explains ``min_anchor_inliers`` points."""
    best = None
    for o in outcomes:
        if o.result is None or k not in (o.i, o.j):
            continue
        r = o.i if o.j == k else o.j
        if not st.registered[r]:
            continue
        g = o.result.geometry
        # a provisional pair's pose is re-estimated at the shared focal found so far
        Rp, tp = _pose_at(o, st.K[o.i], st.K[o.j], PNP_ERROR_PX) if o.provisional else (g.R, g.t)
        R, a, b = pair_anchor(Rp, tp, st.R[r], st.t[r], new_is_second=o.j == k)
        fit = anchored_pose(obj, xy, st.K[k], R, a, b, PNP_ERROR_PX)
        if fit is not None and (best is None or fit[1] > best[2]):
            best = (R, fit[0], fit[1])
    return best if best is not None and best[2] >= MIN_ANCHOR_INLIERS else None


def register_known(views: Sequence[View], tracks: Tracks, R: np.ndarray, t: np.ndarray) -> Registration:
    """Every photo at its given pose (world → camera ``R`` [N, 3, 3], ``t`` [N, 3]): the tracks triangulated from
    them, in their frame and unit; nothing is estimated or adjusted."""
    st = _State(views, tracks)
    for k in range(len(views)):
        st.add(k, R[k], t[k])
    st.triangulate()
    st.measure()
    return _finish(st, [None] * len(views), (0, 1), given_frame=True)


def _finish(st: _State, reasons: list[str | None], init: tuple[int, int], *, given_frame: bool = False) -> Registration:
    """The registration in the output frame: world = the first registered photo (in input order), unit = the
    first pair's baseline (``given_frame``: as it is)."""
    R, t, pts = st.R.copy(), st.t.copy(), st.points.copy()
    reg = np.flatnonzero(st.registered)
    if len(reg) and not given_frame:
        a, b = init
        base = np.linalg.norm(st.R[a].T @ st.t[a] - st.R[b].T @ st.t[b])
        s = 1.0 / base if base > 0 and math.isfinite(base) else 1.0
        w = reg[0]
        Rw, tw = st.R[w].copy(), st.t[w].copy()
        # X' = s (Rw X + tw): camera w becomes the identity, the first pair's baseline 1
        for k in reg:
            R[k] = st.R[k] @ Rw.T
            t[k] = s * (st.t[k] - R[k] @ tw)
        pts = s * (st.points @ Rw.T + tw)
    keep = st.inlier
    return Registration(R, t, st.K.copy(), st.registered.copy(), reasons, pts, st.point_ok.copy(),
                        st.tracks.subset(keep), np.nan_to_num(st.residual[keep], nan=np.inf), init, list(st.order),
                        st.focal_group >= 0)  # fmt: skip
