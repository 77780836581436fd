"""The pose of a planar scene (issue 14): a plane seen from two views fits two relative poses.

When a homography explains :data:`~.essential.PLANAR_FRACTION` of the verified matches, the essential matrix's pose
and the poses of the homography's decomposition compete: those that explain as many verified matches contend, and
all the matches decide — the verified ones and those below the confidence gate (``Matches.below_gate``): a pose wins
with matches it explains (in front of both cameras) that the other refutes (behind a camera: the plane's wrong pose
often puts part of it there; or far off its epipolar lines: points off the plane). Tied evidence is refused
(:class:`~macsplat_cli.errors.PlaneTieError`), and a later descriptor tier's pose must settle the same contest on
its own matches (:func:`settles_tie`), whatever share of them the plane holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ...camera_math import scale_focal
from ...errors import PlaneTieError
from ...metrics import angle_between_deg, rotation_angle_deg
from ..types import Matches, TwoViewGeometry
from .config import SAME_POSE_DEG, PoseConfig
from .diagnostics import PoseDiagnostics
from .geometry import MIN_TRANSLATION, decompose_homography, epipolar_fit, homog, parallax_deg, same_pose, support
from .refit import POSE_LM, refit_pose

__all__ = ["PlanarVerdict", "ambiguous", "planar_pose", "resolve_planar", "settles_tie"]

DIRECTION_WEIGHT = 3
"""In ``planar_agreement_deg`` a translation-direction difference counts a third of a rotation difference (the
direction of a short baseline is the less determined)."""
SAME_SOLUTION_DEG = (2.0, 10.0)
"""Two poses within this (rotation, translation direction, °) are one solution found twice (a decomposition and
the essential matrix's pose, or a refit sliding along a plane's valley): no ambiguity between them."""
PLANAR_CONTEND = 0.8
"""A plane's pose that explains at least this fraction of the best one's verified matches contends: it must be
beaten by evidence, not by a count a few matches short."""
PLANAR_MIN_EVIDENCE = 8
"""Fewest matches that the winning pose must explain and each rival refute."""
PLANAR_EVIDENCE_RATIO = 3.0
"""How many times the converse count (explained by the rival, refuted by the winner) those must be."""
PLANAR_REFUTE_FACTOR = 3.0
"""A pose refutes a match behind one of its cameras or farther than this many ``threshold_px`` from its epipolar
geometry (the band between explained and refuted is no evidence)."""
TIE_HOMOGRAPHY_PX = 1.5
""":func:`settles_tie` fits the matches' homography by RANSAC with this threshold (px), as the evidence's GRIC does."""
TIE_MIN_MATCHES = 15
"""Fewer matches than this and :func:`settles_tie` holds no contest (a homography's four and a pose's five are a
guess)."""


def ambiguous(n_final: int, rival: int, evidence: tuple[int, int] | None = None) -> PlaneTieError:
    """The refusal of a plane's two tied poses."""
    more = f"; no other matches tell them apart ({evidence[0]} against {evidence[1]})" if evidence is not None else ""
    return PlaneTieError(
        f"pose is ambiguous: the {n_final} verified matches lie on one plane, and two different relative "
        f"poses explain them ({rival} and {n_final} matches){more}: photograph more of the scene's depth"
    )


def _candidates(
    R: np.ndarray, t: np.ndarray, H: np.ndarray, *, s: float, K0: np.ndarray, K1: np.ndarray,
    unknown: tuple[bool, bool], xy0: np.ndarray, xy1: np.ndarray, cfg: PoseConfig,
) -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:  # fmt: skip
    """The essential matrix's pose ``(R, t)`` and the distinct poses of ``H``'s decomposition that explain
    ``min_inliers`` gated matches, each refined on those; and how far ``(R, t)`` is from the nearest decomposition
    (``planar_agreement_deg``)."""
    K0s = scale_focal(K0, s) if unknown[0] else K0
    K1s = scale_focal(K1, s) if unknown[1] else K1
    candidates: list[tuple[np.ndarray, np.ndarray]] = [(R, t)]
    agreement = math.inf
    Rs, ts = decompose_homography(np.linalg.inv(K1s) @ H @ K0s)
    for Ri, ti in zip(Rs, ts):
        ti = ti.ravel()
        if np.linalg.norm(ti) < MIN_TRANSLATION:
            continue
        ti = ti / np.linalg.norm(ti)
        agreement = min(
            agreement, max(rotation_angle_deg(Ri @ R.T), float(angle_between_deg(ti, t)) / DIRECTION_WEIGHT)
        )
        sup = support(Ri, ti, K0s, K1s, xy0, xy1, cfg.threshold_px)
        if sup.sum() < cfg.min_inliers:
            continue
        if cfg.refine:
            fit = refit_pose(
                Ri, ti, K0, K1, xy0[sup], xy1[sup], scale_px=cfg.threshold_px, schedule=POSE_LM, log_focal=s,
                unknown=unknown,
            )  # fmt: skip
            collapsed = any(same_pose(fit.R, fit.t, Rc, tc, SAME_POSE_DEG) for Rc, tc in candidates)
            if not (collapsed and not any(same_pose(Ri, ti, Rc, tc, SAME_SOLUTION_DEG) for Rc, tc in candidates)):
                Ri, ti = fit.R, fit.t
            # else: refined, a distinct decomposition slid onto another candidate (the planar valley: a plane with
            # little rotation fits a range of translations). It stays as it was, a rival the evidence must beat
        if not any(same_pose(Ri, ti, Rc, tc, SAME_POSE_DEG) for Rc, tc in candidates):
            candidates.append((Ri, ti))
    return candidates, agreement


def _usable(
    candidates: list[tuple[np.ndarray, np.ndarray]], masks: list[np.ndarray], gated: list[int], x0n: np.ndarray,
    x1n: np.ndarray, cfg: PoseConfig,
) -> list[int]:  # fmt: skip
    """The candidates (indices, best supported first) with a median parallax of ``min_parallax_deg``, one per
    solution: the same solution twice (the essential matrix's and a decomposition's, a few degrees apart) is no
    ambiguity, the better supported stands for both. A wrong essential matrix on a plane can look like a rotation;
    a true rotation keeps the essential pose and is refused for its baseline."""
    parallax = [
        float(np.median(parallax_deg(Rc, x0n[m], x1n[m]))) if m.any() else 0.0 for (Rc, _), m in zip(candidates, masks)
    ]
    usable: list[int] = []
    for k in sorted(range(len(candidates)), key=lambda k: -gated[k]):
        if parallax[k] >= cfg.min_parallax_deg and not any(
            same_pose(*candidates[k], *candidates[j], SAME_SOLUTION_DEG) for j in usable
        ):
            usable.append(k)
    return usable


def _all_matches(xy0: np.ndarray, xy1: np.ndarray, below_gate: Matches | None) -> tuple[np.ndarray, np.ndarray]:
    """The gated matches and those below the gate (when finite). [M', 2] ×2"""
    if below_gate is None or not len(below_gate):
        return xy0, xy1
    if not (np.isfinite(below_gate.xy0).all() and np.isfinite(below_gate.xy1).all()):
        return xy0, xy1
    all0 = np.concatenate([xy0, below_gate.xy0.astype(np.float64)])
    all1 = np.concatenate([xy1, below_gate.xy1.astype(np.float64)])
    return all0, all1


def planar_pose(
    R: np.ndarray, t: np.ndarray, H: np.ndarray, *, log_focal: float, K0: np.ndarray, K1: np.ndarray,
    unknown: tuple[bool, bool], xy0: np.ndarray, xy1: np.ndarray, below_gate: Matches | None, diag: PoseDiagnostics,
    cfg: PoseConfig,
) -> tuple[np.ndarray, np.ndarray, bool]:  # fmt: skip
    """The relative pose of a pair whose matches ``xy0, xy1`` [M, 2] lie mostly on one plane (module docstring).

    ``(R, t)`` is the essential matrix's pose, ``H`` [3, 3] the matches' dominant homography, ``log_focal`` the log
    focal scale of the ``unknown`` views (intrinsics ``K0``, ``K1`` before it), ``below_gate`` the matches below the
    confidence gate; the measurements go to ``diag``.

    Candidates (:func:`_candidates`) that explain :data:`PLANAR_CONTEND` of the best support on the gated matches
    contend; when more than one does, all the matches (gated and ``below_gate``) decide (:func:`resolve_planar`).

    Returns:
        ``(R, t, changed)``: the winner, and whether it differs from the given pose.

    Raises:
        PlaneTieError: the contenders are tied on all the evidence.
    """
    s = log_focal
    K0s = scale_focal(K0, s) if unknown[0] else K0
    K1s = scale_focal(K1, s) if unknown[1] else K1
    Ki0, Ki1 = np.linalg.inv(K0s), np.linalg.inv(K1s)
    x0n, x1n = homog(xy0) @ Ki0.T, homog(xy1) @ Ki1.T
    candidates, agreement = _candidates(R, t, H, s=s, K0=K0, K1=K1, unknown=unknown, xy0=xy0, xy1=xy1, cfg=cfg)
    masks = [support(Rc, tc, K0s, K1s, xy0, xy1, cfg.threshold_px) for Rc, tc in candidates]
    gated = [int(m.sum()) for m in masks]
    usable = _usable(candidates, masks, gated, x0n, x1n, cfg)
    diag.planar_candidates, diag.planar_gated_support = len(candidates), ",".join(map(str, gated))
    diag.planar_rival_inliers, diag.planar_agreement_deg = max(gated[1:], default=0), agreement
    if not usable:
        return R, t, False
    top = max(gated[k] for k in usable)
    contenders = [k for k in usable if gated[k] >= PLANAR_CONTEND * top]
    all0, all1 = xy0, xy1
    if len(contenders) > 1:
        all0, all1 = _all_matches(xy0, xy1, below_gate)
        verdict = resolve_planar([candidates[k] for k in contenders], K0s, K1s, all0, all1, cfg)
        diag.planar_support = ",".join(map(str, verdict.support))
        diag.planar_evidence, diag.planar_counter_evidence = verdict.exclusive
        diag.planar_matches_scored = len(all0)
        if verdict.winner is None:
            ranked = sorted((gated[k] for k in contenders), reverse=True)
            raise ambiguous(ranked[0], ranked[1], verdict.exclusive)
        winner = contenders[verdict.winner]
    else:
        winner = contenders[0]
    diag.planar_resolved = "essential" if winner == 0 else "homography"
    if winner == 0:
        return R, t, False
    R, t = candidates[winner]
    sup = support(R, t, K0s, K1s, all0, all1, cfg.threshold_px)
    if cfg.refine:
        fit = refit_pose(
            R, t, K0, K1, all0[sup], all1[sup], scale_px=cfg.threshold_px, schedule=POSE_LM, log_focal=s,
            unknown=unknown,
        )  # fmt: skip
        R, t = fit.R, fit.t
    return R, t, True


@dataclass
class PlanarVerdict:
    """The outcome of :func:`resolve_planar`: the index of the winning candidate (None: tied), each candidate's
    support over all the matches, and (evidence, counter-evidence) of the best candidate's closest duel."""

    winner: int | None
    support: list[int]
    exclusive: tuple[int, int]


def resolve_planar(
    candidates: list[tuple[np.ndarray, np.ndarray]],
    K0: np.ndarray,
    K1: np.ndarray,
    xy0: np.ndarray,
    xy1: np.ndarray,
    cfg: PoseConfig,
) -> PlanarVerdict:
    """Tell a plane's relative poses apart by the evidence the plane does not give.

    Every candidate explains the plane's matches equally well; what separates them is the matches off the plane
    (which only the true pose explains) and cheirality (the wrong pose of a plane puts part of it behind a
    camera). Each candidate is scored by the matches it explains with positive depth among ``xy0, xy1`` (all
    matches: the verified ones, the rest of the gated ones and those below the confidence gate). The best wins
    when, against every other candidate, the matches it explains (within ``threshold_px``, in front) and the
    other refutes (behind a camera, or beyond ``PLANAR_REFUTE_FACTOR · threshold_px``) number at least
    :data:`PLANAR_MIN_EVIDENCE` and :data:`PLANAR_EVIDENCE_RATIO` times the converse; else the candidates are tied.
    Matches near the threshold of either count for neither: noise there is not evidence.

    Returns:
        the verdict; ``exclusive`` is (evidence, counter-evidence) of the closest duel.
    """
    fits = [epipolar_fit(R, t, K0, K1, xy0, xy1) for R, t in candidates]
    explained = [(d < cfg.threshold_px) & front for d, front in fits]
    refuted = [(d > PLANAR_REFUTE_FACTOR * cfg.threshold_px) | ~front for d, front in fits]
    supports = [int(m.sum()) for m in explained]
    order = np.argsort(supports, kind="stable")[::-1]
    if len(candidates) < 2:
        return PlanarVerdict(int(order[0]) if candidates else None, supports, (0, 0))
    # the best must win every duel: matches it explains and the other refutes, against the converse
    worst: tuple[int, int] | None = None
    for k in order[1:]:
        a = int((explained[order[0]] & refuted[k]).sum())
        b = int((explained[k] & refuted[order[0]]).sum())
        if worst is None or a - PLANAR_EVIDENCE_RATIO * b < worst[0] - PLANAR_EVIDENCE_RATIO * worst[1]:
            worst = (a, b)
    assert worst is not None
    won = worst[0] >= PLANAR_MIN_EVIDENCE and worst[0] >= PLANAR_EVIDENCE_RATIO * worst[1]
    return PlanarVerdict(int(order[0]) if won else None, supports, worst)


def _refit_on(R: np.ndarray, t: np.ndarray, g: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray, thr: float):  # noqa: ANN202
    """``(R, t, support)`` of the pose re-fitted on ``xy0, xy1`` [M, 2] at the geometry's intrinsics."""
    fit = refit_pose(R, t / max(float(np.linalg.norm(t)), 1e-12), g.K0, g.K1, xy0, xy1, scale_px=thr,
                     schedule=POSE_LM, unknown=(False, False))  # fmt: skip
    return fit.R, fit.t, int(support(fit.R, fit.t, g.K0, g.K1, xy0, xy1, thr).sum())


def settles_tie(geometry: TwoViewGeometry, matches: Matches, cfg: PoseConfig) -> bool:
    """Whether ``geometry``, a later tier's pose of a pair on which an earlier tier found a plane's two poses tied,
    wins the same contest on its own ``matches`` (its tier's filtered matches), at the geometry's intrinsics.

    The poses of the matches' homography, each re-fitted on them, that differ from the pose re-fitted the same way
    by more than ``SAME_SOLUTION_DEG``: the best supported contends when it explains :data:`PLANAR_CONTEND` of the
    pose's support (else the pose wins by its count, as in :func:`planar_pose`); then all the matches (gated and
    below the gate) decide (:func:`resolve_planar`), and the pose must win. No share of the matches on the plane is
    asked (``PLANAR_FRACTION``): the earlier tier saw the plane; a tier whose matches lie mostly off it still fits
    its second pose nearly as well (ICL (0, 2), benchmarks/history/pose.md).
    """
    if len(matches) < TIE_MIN_MATCHES:
        return False
    g, thr = geometry, cfg.threshold_px
    xy0, xy1 = matches.xy0.astype(np.float64), matches.xy1.astype(np.float64)
    H, _ = cv2.findHomography(xy0, xy1, cv2.RANSAC, TIE_HOMOGRAPHY_PX)
    if H is None:
        return True  # no plane among these matches: nothing to contest
    R0, t0, own = _refit_on(g.R, g.t, g, xy0, xy1, thr)
    best: tuple[int, tuple[np.ndarray, np.ndarray] | None] = (0, None)
    for R, t in zip(*decompose_homography(np.linalg.inv(g.K1) @ H @ g.K0)):
        t = np.ravel(t) / max(float(np.linalg.norm(t)), 1e-12)
        if support(R, t, g.K0, g.K1, xy0, xy1, thr).sum() < PLANAR_CONTEND * own / 2:
            continue  # most of the plane behind a camera: the decomposition's wrong sign, no rival
        Rc, tc, n = _refit_on(R, t, g, xy0, xy1, thr)
        if n > best[0] and not same_pose(Rc, tc, R0, t0, SAME_SOLUTION_DEG):
            best = (n, (Rc, tc))
    if best[1] is None or best[0] < PLANAR_CONTEND * own:
        return True
    all0, all1 = _all_matches(xy0, xy1, matches.below_gate)
    return resolve_planar([(R0, t0), best[1]], g.K0, g.K1, all0, all1, cfg).winner == 0
