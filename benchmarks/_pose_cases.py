"""What the pose benchmarks share: one pair through the classical pipeline up to the accepted pose, and its outcome.

:func:`pose_case` runs the pose search alone (``Pipeline.search`` on the loaded views; on a checkout before the pose
search object, ``Pipeline.run`` with a depth stage that stops it) with ``accept_low_confidence=True``, so that a
doubted pose comes back with its doubts instead of an error. It uses only names that older checkouts have too, so a
benchmark can run another checkout's library (``PYTHONPATH=/tmp/before:$REPO``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from macsplat_cli.errors import MacsplatError
from macsplat_cli.metrics import rotation_error_deg, translation_direction_error_deg
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig

try:  # the stage factory (a checkout before it took the slots as keywords)
    from macsplat_cli.pipeline.run import classical_stages
except ImportError:
    classical_stages = None  # type: ignore[assignment]
from macsplat_cli.pipeline.views import load_views

RIGHT_DEG = 5.0
"""A pose is right below this rotation error (degrees), wrong at or above it."""


class _Stop(Exception):
    pass


class _StopAtDepth:
    """A depth stage that records the views and the geometry and stops the run (nothing after the pose)."""

    name = "stop"

    def __init__(self) -> None:
        self.geometry: Any = None

    def __call__(self, views: Any, geometry: Any, pair: Any) -> Any:
        self.geometry = geometry
        raise _Stop


def _allow_low_confidence(cfg: ReconstructConfig) -> None:
    if hasattr(cfg, "search"):
        cfg.search.accept_low_confidence = True
    elif hasattr(cfg, "accept_low_confidence"):  # a checkout before the pose search object (issue 24)
        cfg.accept_low_confidence = True


def pose_case(paths: list[Path], cfg: ReconstructConfig, R_gt: np.ndarray, t_gt: np.ndarray) -> dict[str, Any]:
    """The pose of one pair and what the acceptance said (``cfg`` is changed: ``accept_low_confidence``).

    Returns:
        ``{"failed": message, "time_s", "confidence_s"}`` when the pipeline raised; else ``rot`` and ``tdir`` (the
        rotation and translation-direction errors, degrees), ``doubts`` (messages), ``doubt_checks`` (who raised
        each, None on a checkout without typed doubts), ``confidence`` (the score), ``checks`` (every entry of the
        confidence's checks), ``inliers``, ``tier`` (None on a checkout without it), ``time_s`` (to the pose, the
        views' loading included) and ``confidence_s`` (the acceptance's own time).
    """
    _allow_low_confidence(cfg)
    stop = _StopAtDepth()
    pipe = (
        Pipeline(cfg, classical_stages(cfg, depth=stop)) if classical_stages is not None else Pipeline(cfg, depth=stop)
    )
    t0 = time.perf_counter()
    tier = None
    try:
        if hasattr(pipe, "search"):  # the pose search alone: nothing after the pose
            result = pipe.search(load_views(paths, cfg.views))
            g, conf, tier = result.geometry, result.confidence, result.tier
            doubts = [d.message for d in result.doubts]
            doubt_checks = [getattr(d, "check", None) for d in result.doubts]
            confidence, checks = (conf.score, dict(conf.checks)) if conf is not None else (None, {})
            spent = conf.seconds if conf is not None else 0.0
        else:
            try:
                pipe.run(paths)
            except _Stop:
                pass
            g = stop.geometry
            info = g.info
            doubts, confidence = list(info.get("doubts", [])), info.get("confidence")
            doubt_checks = [None] * len(doubts)
            checks, spent = dict(info.get("confidence_checks", {})), 0.0
    except MacsplatError as e:
        return {"failed": str(e), "time_s": time.perf_counter() - t0, "confidence_s": 0.0}
    return {
        "rot": rotation_error_deg(g.R, R_gt),
        "tdir": translation_direction_error_deg(g.t, t_gt),
        "doubts": doubts,
        "doubt_checks": doubt_checks,
        "confidence": confidence,
        "checks": checks,
        "inliers": len(g.inliers),
        "tier": tier,
        "time_s": time.perf_counter() - t0,
        "confidence_s": spent,
    }


def outcome(r: dict[str, Any], *, refusals: bool = True) -> str:
    """``"refused"`` (the pipeline raised, or with ``refusals`` the pose has doubts), else ``"right"`` below
    :data:`RIGHT_DEG` of rotation error and ``"wrong"`` at or above it."""
    if "failed" in r:
        return "refused"
    if refusals and r.get("doubts"):
        return "refused"
    return "right" if r["rot"] < RIGHT_DEG else "wrong"
