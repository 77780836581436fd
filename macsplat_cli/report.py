"""The run report of a reconstruction: typed sections, one ``to_json()``.

The report is written in one place, as the stages finish: the pipeline creates :class:`RunReport` (inputs,
per-stage backends and times, matches, pose, depth, Gaussians) and every later step adds its section through
the report's own ``add_*`` methods — the network's pass (:meth:`RunReport.add_network`), the refinement
(:meth:`RunReport.add_refine`), the compaction (:meth:`RunReport.add_compact`) and, once the files are written,
:meth:`RunReport.add_outputs`. ``to_json()`` gives the JSON document that ``macsplat reconstruct --report/--json``
writes (sections that do not apply are left out).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

from ._json import to_jsonable

__all__ = ["ImageReport", "RefineReport", "RunReport"]


@dataclass
class ImageReport:
    """One input photo: its sizes and where its intrinsics came from."""

    name: str
    original_size: list[int]
    working_size: list[int]
    intrinsics_source: str
    focal_px_working: float


@dataclass
class RefineReport:
    """The test-time refinement (``--refine``)."""

    steps: int
    max_steps: int
    stopped_early: bool
    seconds: float
    scale: int
    mac: bool
    lpips: bool
    loss_first: dict[str, float]
    loss_last: dict[str, float]
    joint: dict[str, Any] | None = None
    """More than two photos: the joint refinement's steps, held-out curve and pose changes
    (:meth:`~macsplat_cli.pipeline.multiview.joint.JointResult.report`)."""


@dataclass
class RunReport:
    """What a reconstruction did (``Reconstruction.report``).

    Attributes:
        macsplat_version: the version that ran.
        inputs: the two photos.
        backends: stage → the backend that ran it.
        times_s: stage → wall seconds, and ``total``.
        images: the photos' sizes and intrinsics.
        keypoints: descriptors per view.
        fallback_used: whether the affine-simulated fallback's matches were kept.
        matches: matches left after each filter, in order.
        inlier_ratio: verified / candidate matches.
        pose: the pose stage's measurements (rotation, parallax, errors, ...).
        depth_coverage: share of pixels with a depth, per view.
        depth_measured: share of pixels with a measured (not filled) depth, per view.
        gaussians: Gaussians in the scene (after the compaction).
        config: every setting, as a dict.
        scale: ``"relative"`` (baseline 1) or ``"metric"``.
        neural: the network's pass (neural backend only).
        refine: the refinement (``--refine`` only).
        compact: what the compaction (``--quality``, ``--budget``) merged and pruned, step by step, and why.
        fill: how many pixels / Gaussians each fill rule gave a depth or placed: ``depth`` (per view, the
            depth stage's rules: measured, filled_edge_aware, filled_push_pull, none, snapped_edge,
            dropped_free_space, from_other_view, slanted_refined, colour_rejected, speckle_removed; see
            :class:`~macsplat_cli.pipeline.depth.FilledDepthMap`) and ``background`` (the far layer's Gaussians
            past each view's border and behind its interior, and the cells the other photo covers).
        multiview: more than two photos: each photo's registration (or why not), each pair's outcome, the
            registration's points and reprojection error (:meth:`~.pipeline.multiview.MultiViewResult.report`).
        gaussians_written: Gaussians in the written PLY (after writing).
        outputs: role → path of each written file (after writing).
    """

    macsplat_version: str
    inputs: list[str]
    backends: dict[str, str | None]
    times_s: dict[str, float]
    images: list[ImageReport]
    keypoints: list[int]
    fallback_used: bool
    matches: dict[str, int]
    inlier_ratio: float | None
    pose: dict[str, Any]
    depth_coverage: list[float]
    depth_measured: list[float | None]
    gaussians: int
    config: dict[str, Any]
    scale: Literal["relative", "metric"] = "relative"
    neural: dict[str, Any] | None = None
    refine: RefineReport | None = None
    compact: dict[str, Any] | None = None
    fill: dict[str, Any] | None = None
    multiview: dict[str, Any] | None = None
    gaussians_written: int | None = None
    outputs: dict[str, str] = field(default_factory=dict)

    def add_time(self, stage: str, seconds: float) -> None:
        """Record a stage's wall time and keep ``total`` the sum."""
        times = {k: v for k, v in self.times_s.items() if k != "total"}
        times[stage] = seconds
        self.times_s = {**times, "total": sum(times.values())}

    def add_network(self, network: str, fusion: str | None, section: dict[str, Any]) -> None:
        """The neural backend's pass: the ``network`` and ``fusion`` backends and the ``neural`` section."""
        self.backends["network"] = network
        self.backends["fusion"] = fusion
        self.neural = section

    def add_refine(self, refine: RefineReport, gaussians: int) -> None:
        """The refinement's section and time; ``gaussians``: the scene's count after it."""
        self.refine = refine
        self.add_time("refine", refine.seconds)
        self.gaussians = gaussians

    def add_compact(self, compact: dict[str, Any], seconds: float, gaussians: int) -> None:
        """The compaction's section (:meth:`~macsplat_cli.pipeline.compact.CompactReport.to_dict`) and time;
        ``gaussians``: the scene's count after it."""
        self.compact = compact
        self.gaussians = gaussians
        self.add_time("compact", seconds)

    def add_outputs(self, outputs: dict[str, Any], *, gaussians_written: int | None = None) -> None:
        """Role → path of each written file, and the Gaussians the PLY holds (when it was written)."""
        if gaussians_written is not None:
            self.gaussians_written = gaussians_written
        self.outputs = {k: str(v) for k, v in outputs.items()}

    def to_json(self) -> dict[str, Any]:
        """The report as plain JSON values (sections that do not apply left out; NaN → null)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for optional in ("neural", "refine", "compact", "fill", "multiview", "gaussians_written"):
            if out[optional] is None:
                del out[optional]
        if not out["outputs"]:
            del out["outputs"]
        return to_jsonable(out)
