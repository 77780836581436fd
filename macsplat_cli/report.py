"""The run report of a reconstruction: typed sections, one ``to_json()``.

The report is written in one place, as the stages finish: the pipeline creates :class:`RunReport` (inputs,
per-stage backends and times, matches, pose, depth, Gaussians) and every later step adds its section through
the report's own ``add_*`` methods — the network's pass (:meth:`RunReport.add_network`), the refinement
(:meth:`RunReport.add_refine`), the compaction (:meth:`RunReport.add_compact`) and, once the files are written,
:meth:`RunReport.add_outputs`. ``to_json()`` gives the JSON document that ``macsplat reconstruct --report/--json``
writes (sections that do not apply are left out). The sections are dataclasses (:class:`ImageReport`,
:class:`RefineReport`, :class:`CompactReport`, :class:`NeuralReport`, :class:`FillReport`) but ``pose`` and
``multiview``, still the dicts their stages build (:meth:`~macsplat_cli.pipeline.pose.PoseResult.report`,
:meth:`~macsplat_cli.pipeline.multiview.MultiViewResult.report`); readers such as ``reconstruct``'s summary read the
typed fields.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

from ._json import to_jsonable

__all__ = [
    "CompactReport", "CompactStep", "FillReport", "FusionReport", "ImageReport", "NeuralReport", "RefineReport",
    "RunReport",
]  # fmt: skip


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
class CompactStep:
    """One step of the compaction (:func:`~macsplat_cli.pipeline.compact.compact`): Gaussians before and after it,
    its time and why it removed what it did."""

    name: str
    before: int
    after: int
    seconds: float
    reason: str


@dataclass
class CompactReport:
    """What the compaction (:func:`~macsplat_cli.pipeline.compact.compact`) did: the report's ``compact`` section.

    Attributes:
        preset: the settings' name.
        before: Gaussians in the maps (valid pixels).
        after: Gaussians returned.
        sh_degree_before: SH degree of the maps.
        sh_degree_after: SH degree of the result.
        seconds: wall time of the whole compaction.
        steps: each step that ran, in order.
    """

    preset: str
    before: int
    after: int
    sh_degree_before: int
    sh_degree_after: int
    seconds: float
    steps: list[CompactStep] = field(default_factory=list)

    @property
    def ratio(self) -> float:
        """``before / after`` (inf for an empty result)."""
        return self.before / self.after if self.after else math.inf

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON values for the run report."""
        out = to_jsonable(self)
        out["ratio"] = to_jsonable(self.ratio)
        return out

    def summary(self) -> str:
        """One line: counts and the reduction."""
        fewer = f"{self.ratio:.1f}× fewer, {self.preset}"
        return f"{self.before} → {self.after} Gaussians ({fewer}) in {self.seconds:.2f} s"


@dataclass
class FusionReport:
    """The semantic fusion of the network's pass (``neural.fusion``).

    Attributes:
        applied: the descriptors are the fused ones.
        detail: what ran, in words.
        policy: ``"auto"`` when the fusion runs only if the backbone's descriptors verify too few matches, else None.
        on_demand_s: the seconds of a fusion that ran on demand.
        matches_kept: on demand: whose matches the pose kept (the fused, or the unfused when they verified more).
    """

    applied: bool
    detail: str
    policy: Literal["auto"] | None = None
    on_demand_s: float | None = None
    matches_kept: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The section as written (the keys that apply, in the report's order)."""
        if self.policy is not None and not self.applied:  # deferred, and never needed
            out: dict[str, Any] = {"applied": False, "policy": self.policy, "detail": self.detail}
        else:
            out = {"applied": self.applied, "detail": self.detail}
            if self.policy is not None:
                out.update(policy=self.policy, on_demand_s=self.on_demand_s)
        if self.matches_kept is not None:
            out["matches_kept"] = self.matches_kept
        return out


@dataclass
class NeuralReport:
    """The network's pass (the neural backend's ``neural`` section).

    Attributes:
        device: where the network ran.
        network: the network, in words.
        network_size: (W, H) of the network's input, or None before a pass.
        forward_s: the forward pass's seconds, or None before a pass.
        fusion: the semantic fusion.
        gaussian_head: the network has a Gaussian head.
        config: the neural stages' settings.
        files: role → the checkpoint file loaded.
        load_s: seconds spent loading the models.
    """

    device: str
    network: str
    network_size: list[int] | None
    forward_s: float | None
    fusion: FusionReport
    gaussian_head: bool
    config: dict[str, Any]
    files: dict[str, str] = field(default_factory=dict)
    load_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        """The section as written."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["fusion"] = self.fusion.to_json()
        return to_jsonable(out)


@dataclass
class FillReport:
    """How many pixels / Gaussians each fill rule gave a depth or placed (the report's ``fill`` section).

    Attributes:
        depth: per view, the depth stage's rules (measured, filled_edge_aware, filled_push_pull, none,
            snapped_edge, dropped_free_space, from_other_view, slanted_refined, colour_rejected, speckle_removed; see
            :class:`~macsplat_cli.pipeline.depth.FilledDepthMap`) → pixels, or None for a depth without them.
        background: the far layer's Gaussians past each view's border and behind its interior, and the cells the
            other photo covers, by rule; None without a far layer.
    """

    depth: list[dict[str, int] | None]
    background: dict[str, int] | None = None


@dataclass
class RunReport:
    """What a reconstruction did (``Reconstruction.report``).

    Attributes:
        macsplat_version: the version that ran.
        inputs: the photos.
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
        fill: how many pixels / Gaussians each fill rule gave a depth or placed.
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
    neural: NeuralReport | None = None
    refine: RefineReport | None = None
    compact: CompactReport | None = None
    fill: FillReport | None = None
    multiview: dict[str, Any] | None = None
    gaussians_written: int | None = None
    outputs: dict[str, str] = field(default_factory=dict)

    def add_time(self, stage: str, seconds: float) -> None:
        """Record a stage's wall time and keep ``total`` the sum."""
        times = {k: v for k, v in self.times_s.items() if k != "total"}
        times[stage] = seconds
        self.times_s = {**times, "total": sum(times.values())}

    def add_network(self, network: str, fusion: str | None, section: NeuralReport) -> None:
        """The neural backend's pass: the ``network`` and ``fusion`` backends and the ``neural`` section."""
        self.backends["network"] = network
        self.backends["fusion"] = fusion
        self.neural = section

    def add_refine(self, refine: RefineReport, gaussians: int) -> None:
        """The refinement's section and time; ``gaussians``: the scene's count after it."""
        self.refine = refine
        self.add_time("refine", refine.seconds)
        self.gaussians = gaussians

    def add_compact(self, compact: CompactReport, gaussians: int) -> None:
        """The compaction's section and time; ``gaussians``: the scene's count after it."""
        self.compact = compact
        self.gaussians = gaussians
        self.add_time("compact", compact.seconds)

    def add_outputs(self, outputs: dict[str, Any], *, gaussians_written: int | None = None) -> None:
        """Role → path of each written file, and the Gaussians the PLY holds (when it was written)."""
        if gaussians_written is not None:
            self.gaussians_written = gaussians_written
        self.outputs = {k: str(v) for k, v in outputs.items()}

    def to_json(self) -> dict[str, Any]:
        """The report as plain JSON values (sections that do not apply left out; NaN → null)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if self.compact is not None:
            out["compact"] = self.compact.to_dict()
        if self.neural is not None:
            out["neural"] = self.neural.to_json()
        for optional in ("neural", "refine", "compact", "fill", "multiview", "gaussians_written"):
            if out[optional] is None:
                del out[optional]
        if not out["outputs"]:
            del out["outputs"]
        return to_jsonable(out)
