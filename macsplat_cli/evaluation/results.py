"""What the evaluation protocol is given and what it measures: :class:`EvalConfig` (the settings), :class:`CaseResult`
(one case, per target :class:`TargetResult`) and :class:`EvalRun` (a run: its cases and the results so far).

The protocol that fills them is in :mod:`.protocol`; :mod:`.summary` and :mod:`.result_files` read them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import torch

from .._json import to_jsonable
from ..datasets.coverage import DEPTH_ATOL, DEPTH_RTOL
from .baselines import PointsConfig
from .metrics import FAILED_POSE_ERROR_DEG, pose_error_deg
from .reconstructors import ReconstructSettings
from .splits import EvalCase

__all__ = ["BASELINES", "CaseResult", "EvalConfig", "EvalRun", "Status", "TargetResult"]

BASELINES = ("points", "copy")
"""The baselines measured on the same targets (:mod:`.baselines`)."""
Status = Literal["ok", "failed", "error"]


@dataclass
class EvalConfig:
    """Args:
    settings: working size and intrinsics mode, shared by every reconstructor.
    eval_size: long side of the resolution at which targets are rendered and compared
        (sides rounded to multiples of 16, like the working size); None: the working size.
        Fix it to compare reconstructions made at different working sizes.
    splatt3r_compatible: image metrics in Splatt3R's convention (mask-then-compare,
        channel-summed masked PSNR; see :mod:`.metrics`).
    baselines: which baselines to measure (subset of :data:`BASELINES`).
    points: how the point-cloud baseline draws its discs.
    depth_atol: absolute depth tolerance of the visibility mask (scene units).
    depth_rtol: relative depth tolerance of the visibility mask.
    background: colour behind the Gaussians and the discs (Splatt3R: black).
    lpips: an LPIPS model (:func:`macsplat_cli.lpips.load_lpips`); None: no LPIPS.
    """

    settings: ReconstructSettings = field(default_factory=ReconstructSettings)
    eval_size: int | None = None
    splatt3r_compatible: bool = False
    baselines: tuple[str, ...] = BASELINES
    points: PointsConfig = field(default_factory=PointsConfig)
    depth_atol: float = DEPTH_ATOL
    depth_rtol: float = DEPTH_RTOL
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lpips: torch.nn.Module | None = None


@dataclass
class TargetResult:
    """Image metrics of one target view, per method (the reconstruction's name and the baselines')."""

    index: int
    name: str
    size: tuple[int, int]
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)


@dataclass
class CaseResult:
    """Everything measured on one case.

    Attributes:
        case: the case.
        method: the reconstructor's name.
        status: ``"ok"``, ``"failed"`` (ReconstructionError) or ``"error"`` (bad input).
        error: the error message, if any.
        time_s: wall time of the reconstruction.
        rotation_error_deg: relative rotation error (NaN unless ok).
        translation_error_deg: translation-direction error (NaN unless ok).
        focal_error_pct: per context view, ``100 · (f_est / f_true − 1)``; None where the
            intrinsics were given (or the view was not registered).
        depth: depth metrics averaged over the (registered) context views (empty without depth).
        scale: the factor ``s`` from reconstruction units to scene units.
        targets: per target, the image metrics.
        registered: the context frames the reconstruction registered (None: not reconstructed).
        unregistered: more than two contexts: each context frame left unregistered, ``{frame, name, reason}``.
        pairs: more than two contexts: every registered pair's errors, ``{context: [i, j], rotation_error_deg,
            translation_error_deg}`` (the case's errors are their means).
    """

    case: EvalCase
    method: str
    status: Status = "ok"
    error: str | None = None
    time_s: float = math.nan
    rotation_error_deg: float = math.nan
    translation_error_deg: float = math.nan
    focal_error_pct: list[float | None] = field(default_factory=lambda: [None, None])
    depth: dict[str, float] = field(default_factory=dict)
    scale: float = math.nan
    targets: list[TargetResult] = field(default_factory=list)
    registered: list[int] | None = None
    unregistered: list[dict[str, Any]] = field(default_factory=list)
    pairs: list[dict[str, Any]] = field(default_factory=list)

    @property
    def pose_error_deg(self) -> float:
        """``max(rotation, translation)`` error; 180° for a failure (NaN for an input error)."""
        if self.status == "error":
            return math.nan
        if self.status == "failed":
            return FAILED_POSE_ERROR_DEG
        return pose_error_deg(self.rotation_error_deg, self.translation_error_deg)

    def to_dict(self) -> dict[str, Any]:
        return to_jsonable(
            {
                **self.case.to_dict(),
                "method": self.method,
                "status": self.status,
                "error": self.error,
                "time_s": self.time_s,
                "rotation_error_deg": self.rotation_error_deg,
                "translation_error_deg": self.translation_error_deg,
                "pose_error_deg": self.pose_error_deg,
                "focal_error_pct": self.focal_error_pct,
                "depth": self.depth,
                "scale": self.scale,
                "targets": [
                    {"index": t.index, "name": t.name, "size": list(t.size), "metrics": t.metrics} for t in self.targets
                ],
                "registered": None if self.registered is None else len(self.registered),
                "registered_contexts": self.registered,
                "unregistered": self.unregistered,
                **({"pairs": self.pairs} if self.pairs else {}),
            }
        )


@dataclass
class EvalRun:
    """A run: its settings and the results so far."""

    dataset: str
    layout: str
    method: str
    config: EvalConfig
    cases: list[EvalCase]
    results: list[CaseResult] = field(default_factory=list)

    @property
    def context_views(self) -> int:
        """Context frames per case (2 without cases)."""
        return max((len(c.context) for c in self.cases), default=2)

    @property
    def complete(self) -> bool:
        return len(self.results) == len(self.cases)

    @property
    def errors(self) -> list[CaseResult]:
        return [r for r in self.results if r.status == "error"]

    @property
    def failures(self) -> list[CaseResult]:
        return [r for r in self.results if r.status == "failed"]
