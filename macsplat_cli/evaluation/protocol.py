"""The evaluation protocol: one test case, a whole run, its summary, and results written as they come.

**One case** (:func:`evaluate_case`): the reconstructor gets the two context photos (and,
with ``intrinsics="given"``, their true intrinsics); it estimates the relative pose itself.
Then

* pose: rotation and translation-direction error of its relative pose against the truth;
  focal error (% of the true focal length, per view) when the intrinsics were not given;
* depth (scenes with depth): AbsRel and δ<1.25 of each context view's depth map at the
  working size, the estimate multiplied by the scale factor below;
* views: every target is rendered from its **true** camera expressed in the camera-0
  frame, ``inv(T_target←world) ∘ T_world←cam0``; when the reconstruction's scale is
  relative its translation is divided by the estimated-to-true baseline ratio
  ``s = |t_true| / |t_est|`` (the same ``s`` scales depth); its intrinsics are the true
  ones at the working size, the focal lengths multiplied by the estimated-to-true ratio of
  context view 0 (1 with given intrinsics), so a reconstruction made with a wrong focal
  length is viewed consistently. Images are compared at the working size (long side
  ``size``, sides multiples of 16; the photo area-resized as the pipeline does; or at
  ``eval_size``), with the
  Splatt3R visibility mask of the target against both context views when the scene has
  depth (:mod:`macsplat_cli.datasets.coverage`), by :func:`.metrics.image_metrics`;
* baselines on the same targets (:mod:`.baselines`): ``points`` (the reconstruction's
  coloured points as opaque discs) and ``copy`` (the nearer context photo);
* wall time of the reconstruction (refinement included).

A :class:`~macsplat_cli.errors.ReconstructionError` makes the case a **failure**: it stays
in the results, counts as a 180° pose error in the AUC, and has no image metrics (the copy
baseline is still measured). Bad input met during a case (an unreadable image) makes it
an **error**: recorded with its message, left out of every statistic, and the run goes on.

**A run** (:func:`evaluate`) first checks every case's context views against the pipeline's
minimum photo size (:func:`check_context_sizes`, from the cameras, whose sizes the data set's
loader matched to the image headers: no pixel is read), so such bad input stops the run before
the first reconstruction; then it evaluates the cases in order. With a :class:`ResultWriter`,
``cases.jsonl``, ``results.json`` and ``results.csv`` are rewritten (atomically) after every case,
so an interrupted run keeps everything it finished.

**Summary** (:func:`summarize`): per split and method, image metrics averaged over targets
(the reconstruction and ``points`` over the targets of successful cases, ``copy`` over
the targets of all evaluated cases), median pose and focal errors over successful cases,
AUC over successful and failed cases, depth metrics averaged over successful cases, and
the mean reconstruction time.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from .._atomic import atomic_write_text, check_folder, check_writable
from .._json import to_jsonable
from ..cameras import Camera
from ..datasets import EvalDataset, EvalScene, resize_depth_nearest
from ..errors import DatasetError, InputError, OutputPathError, ReconstructionError
from ..metrics import rotation_error_deg, translation_direction_error_deg
from ..pipeline.run import Reconstruction
from ..pipeline.views import MIN_IMAGE_SIDE, working_size
from ..render import render_camera
from .baselines import PointsConfig, nearest_context, point_cloud, render_points
from ..datasets.coverage import DEPTH_ATOL, DEPTH_RTOL, visibility_mask
from .metrics import AUC_THRESHOLDS_DEG, FAILED_POSE_ERROR_DEG, depth_metrics, image_metrics, pose_auc, pose_error_deg
from .reconstructors import Reconstructor, ReconstructSettings
from .splits import SPLITS, EvalCase

__all__ = [
    "BASELINES",
    "CaseResult",
    "EvalConfig",
    "EvalRun",
    "ResultWriter",
    "TargetResult",
    "check_context_sizes",
    "evaluate",
    "evaluate_case",
    "summarize",
    "summary_markdown",
    "target_camera",
    "to_jsonable",
]

logger = logging.getLogger(__name__)

BASELINES = ("points", "copy")
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
            intrinsics were given.
        depth: depth metrics averaged over the two context views (empty without depth).
        scale: the factor ``s`` from reconstruction units to scene units.
        targets: per target, the image metrics.
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
    def complete(self) -> bool:
        return len(self.results) == len(self.cases)

    @property
    def errors(self) -> list[CaseResult]:
        return [r for r in self.results if r.status == "error"]

    @property
    def failures(self) -> list[CaseResult]:
        return [r for r in self.results if r.status == "failed"]


# ------------------------------------------------------------------------------------ one case
def _working_camera(cam: Camera, size: int) -> Camera:
    return cam.rescaled(*working_size(cam.width, cam.height, size))


def target_camera(
    target: Camera, context0: Camera, *, scale: float, width: int, height: int, focal_ratio: tuple[float, float]
) -> Camera:
    """The true target camera in the reconstruction's frame (camera 0, reconstruction units).

    Args:
        target: the target's true camera (world frame of the data set).
        context0: context view 0's true camera.
        scale: ``s``, reconstruction units → scene units (the translation is divided by it).
        width: render width.
        height: render height.
        focal_ratio: (fx, fy) multipliers of the true focal lengths.
    """
    T = target.world_to_cam @ context0.cam_to_world  # camera 0 → target
    T[:3, 3] /= scale
    K = target.rescaled(width, height).K.copy()
    K[0, 0] *= focal_ratio[0]
    K[0, 1] *= focal_ratio[0]
    K[1, 1] *= focal_ratio[1]
    return Camera(target.name, width, height, K, np.linalg.inv(T))


def _resize_to(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    return resize_depth_nearest(depth, width, height) if depth.shape != (height, width) else depth


def evaluate_case(
    scene: EvalScene, case: EvalCase, reconstructor: Reconstructor, config: EvalConfig | None = None
) -> CaseResult:
    """Reconstruct one case and measure it (module docstring).

    Returns:
        The result, with status ``"ok"`` or ``"failed"``.

    Raises:
        InputError: bad input met on the way (unreadable image or depth map).
    """
    cfg = config or EvalConfig()
    size = cfg.eval_size or cfg.settings.size
    frames = scene.frames
    gt = [frames[c].camera for c in case.context]
    res = CaseResult(case, reconstructor.name)

    # ground truth of the targets, independent of the reconstruction
    ctx_cams_w = [_working_camera(frames[c].camera, size) for c in case.context]
    ctx_depth = [scene.depth(c, (cam.width, cam.height)) for c, cam in zip(case.context, ctx_cams_w)]
    known = [d for d in ctx_depth if d is not None]
    has_depth = len(known) == len(ctx_depth)
    photos: dict[tuple[int, tuple[int, int]], np.ndarray] = {}

    def photo(index: int, wh: tuple[int, int]) -> np.ndarray:
        if (index, wh) not in photos:
            photos[(index, wh)] = scene.rgb(index, wh)
        return photos[(index, wh)]

    targets = []
    for ti in case.targets:
        cam_w = _working_camera(frames[ti].camera, size)
        wh = (cam_w.width, cam_w.height)
        image = scene.rgb(ti, wh)
        mask = None
        if has_depth:
            d_t = scene.depth(ti, wh)
            if d_t is not None:
                mask = visibility_mask(d_t, cam_w, known, ctx_cams_w, atol=cfg.depth_atol, rtol=cfg.depth_rtol)
        tr = TargetResult(ti, frames[ti].name, wh)
        if "copy" in cfg.baselines:
            near = case.context[nearest_context(frames[ti].camera, (gt[0], gt[1]))]
            tr.metrics["copy"] = image_metrics(
                photo(near, wh), image, mask, splatt3r=cfg.splatt3r_compatible, lpips=cfg.lpips
            )
        targets.append((tr, image, mask))
    res.targets = [t[0] for t in targets]

    t0 = time.perf_counter()
    try:
        rec: Reconstruction = reconstructor(scene, case, cfg.settings)
    except ReconstructionError as e:
        res.time_s = time.perf_counter() - t0
        res.status, res.error = "failed", " ".join(str(e).split())
        logger.info("%s: reconstruction failed: %s", case.key, res.error)
        return res
    res.time_s = time.perf_counter() - t0

    # pose, focal length, scale
    T_gt = gt[1].world_to_cam @ gt[0].cam_to_world
    g = rec.geometry
    res.rotation_error_deg = rotation_error_deg(g.R, T_gt[:3, :3])
    res.translation_error_deg = translation_direction_error_deg(g.t, T_gt[:3, 3])
    t_est = float(np.linalg.norm(g.t))
    res.scale = float(np.linalg.norm(T_gt[:3, 3])) / t_est if rec.scale == "relative" and t_est > 0 else 1.0
    K_est = (g.K0, g.K1)
    ratios = []
    for k, v in enumerate(rec.views):
        K_true = gt[k].rescaled(v.width, v.height).K
        ratios.append((K_est[k][0, 0] / K_true[0, 0], K_est[k][1, 1] / K_true[1, 1]))
        if v.intrinsics_source != "file":
            res.focal_error_pct[k] = 100.0 * (ratios[k][0] - 1.0)

    # depth of the context views
    if has_depth and rec.depths:
        per_view = []
        for k, dm in enumerate(rec.depths):
            h, w = dm.depth.shape
            d_true = _resize_to(scene.depth(case.context[k]), w, h)  # type: ignore[arg-type]
            est = np.where(dm.valid, dm.depth, 0.0)
            per_view.append(depth_metrics(est, d_true, res.scale))
        res.depth = {key: _mean([m[key] for m in per_view]) for key in per_view[0]}

    # target views
    points = point_cloud(rec.gaussians, cfg.points) if "points" in cfg.baselines else None
    for tr, image, mask in targets:
        cam = target_camera(
            frames[tr.index].camera, gt[0], scale=res.scale, width=tr.size[0], height=tr.size[1], focal_ratio=ratios[0]
        )
        with torch.no_grad():
            out = render_camera(rec.gaussians, cam, background=cfg.background)
        pred = out.rgb.clamp(0.0, 1.0).cpu().numpy()
        m = image_metrics(pred, image, mask, splatt3r=cfg.splatt3r_compatible, lpips=cfg.lpips)
        m["alpha_coverage"] = float((out.alpha > 0.5).float().mean())
        tr.metrics[res.method] = m
        if points is not None:
            rgb, covered = render_points(points, cam, background=cfg.background, config=cfg.points)
            pm = image_metrics(rgb, image, mask, splatt3r=cfg.splatt3r_compatible, lpips=cfg.lpips)
            pm["alpha_coverage"] = float(covered.mean())
            tr.metrics["points"] = pm
    return res


# ------------------------------------------------------------------------------------ a run
def check_context_sizes(dataset: EvalDataset, cases: Sequence[EvalCase] | None = None) -> None:
    """Refuse, before any reconstruction, context views smaller than the pipeline accepts (``MIN_IMAGE_SIDE``).

    The sizes are the cameras', which the loaders matched to the image headers (EXIF orientation
    applied), so no file is read. ``cases`` None checks every frame of every scene (any frame may
    be drawn as a context view when the cases are made from the splits). O(frames + cases).

    Raises:
        DatasetError: naming the image, its size and the case (or the scene).
    """
    scenes = {s.name: s for s in dataset.scenes}
    if cases is None:
        todo = [(s, i, f"scene {s.name!r}") for s in dataset.scenes for i in range(len(s.frames))]
    else:
        todo = [(scenes[c.scene], i, f"case {c.key}") for c in cases if c.scene in scenes for i in c.context]
    for scene, i, where in todo:
        f = scene.frames[i]
        w, h = f.camera.width, f.camera.height
        if min(w, h) < MIN_IMAGE_SIDE:
            raise DatasetError(
                f"{f.image}: {w}x{h} px is too small for a context view ({where}); at least {MIN_IMAGE_SIDE} px "
                "on each side are needed"
            )


def evaluate(
    dataset: EvalDataset,
    cases: Sequence[EvalCase],
    reconstructor: Reconstructor,
    config: EvalConfig | None = None,
    *,
    writer: ResultWriter | None = None,
    on_case: Callable[[int, EvalCase, CaseResult | None], None] | None = None,
) -> EvalRun:
    """Evaluate ``cases`` in order (module docstring).

    Args:
        dataset: the data set the cases refer to.
        cases: the cases.
        reconstructor: what reconstructs them.
        config: settings.
        writer: writes results after every case.
        on_case: called with ``(index, case, None)`` before and ``(index, case, result)`` after each case.

    Returns:
        The run (every case has a result; bad input in a case is recorded as an error).

    Raises:
        DatasetError: a context view too small for the pipeline (:func:`check_context_sizes`),
            before the first case.
    """
    cfg = config or EvalConfig()
    check_context_sizes(dataset, cases)
    run = EvalRun(str(dataset.root), dataset.layout, reconstructor.name, cfg, list(cases))
    if writer is not None:
        writer.start(run)
    for i, case in enumerate(run.cases):
        if on_case is not None:
            on_case(i, case, None)
        try:
            res = evaluate_case(dataset.scene(case.scene), case, reconstructor, cfg)
        except InputError as e:
            res = CaseResult(case, reconstructor.name, status="error", error=" ".join(str(e).split()))
            logger.warning("%s: not evaluated: %s", case.key, res.error)
        run.results.append(res)
        if writer is not None:
            writer.add(run, res)
        if on_case is not None:
            on_case(i, case, res)
    return run


# ------------------------------------------------------------------------------------ summary
def _mean(values: Sequence[float]) -> float:
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if len(v) else math.nan


def _median(values: Sequence[float | None]) -> float:
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[~np.isnan(v)]
    return float(np.median(v)) if len(v) else math.nan


_IMAGE_KEYS = ("psnr", "ssim", "psnr_masked", "ssim_masked", "lpips")


def _image_summary(results: Sequence[CaseResult], method: str) -> dict[str, float]:
    per_target = [t.metrics[method] for r in results for t in r.targets if method in t.metrics]
    out: dict[str, float] = {"targets": len(per_target)}
    for key in _IMAGE_KEYS:
        out[key] = _mean([m.get(key, math.nan) for m in per_target])
    return out


def summarize(run: EvalRun) -> list[dict[str, Any]]:
    """One row per split (and ``all`` when there are several) and method; see the module docstring."""
    splits = [s for s in SPLITS if any(r.case.split == s for r in run.results)]
    splits += sorted({r.case.split for r in run.results} - set(SPLITS))
    groups = [(s, [r for r in run.results if r.case.split == s]) for s in splits]
    if len(groups) > 1:
        groups.append(("all", list(run.results)))
    rows = []
    for split, results in groups:
        evaluated = [r for r in results if r.status != "error"]
        ok = [r for r in evaluated if r.status == "ok"]
        row: dict[str, Any] = {
            "split": split,
            "method": run.method,
            "cases": len(evaluated),
            "failed": len(evaluated) - len(ok),
            "errors": len(results) - len(evaluated),
            **_image_summary(ok, run.method),
            "rotation_error_deg": _median([r.rotation_error_deg for r in ok]),
            "translation_error_deg": _median([r.translation_error_deg for r in ok]),
            **pose_auc([r.pose_error_deg for r in evaluated], AUC_THRESHOLDS_DEG),
            "focal_error_pct": _median([abs(f) for r in ok for f in r.focal_error_pct if f is not None]),
            "depth_absrel": _mean([r.depth.get("absrel", math.nan) for r in ok]),
            "depth_delta1": _mean([r.depth.get("delta1", math.nan) for r in ok]),
            "time_s": _mean([r.time_s for r in evaluated]),
        }
        rows.append(row)
        for base in run.config.baselines:
            src = ok if base == "points" else evaluated
            rows.append({"split": split, "method": base, "cases": len(src), **_image_summary(src, base)})
    return rows


def format_cell(v: Any, digits: int = 2) -> str:
    """A table cell: floats to ``digits`` decimals, None/NaN/inf as "–"."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def summary_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The summary as two Markdown tables: novel views per method, then pose, depth and time."""
    views = (
        ("psnr", "PSNR", 2),
        ("ssim", "SSIM", 3),
        ("psnr_masked", "masked PSNR", 2),
        ("ssim_masked", "masked SSIM", 3),
        ("lpips", "LPIPS", 3),
    )
    geo = (
        ("rotation_error_deg", "rot err °", 2), ("translation_error_deg", "t err °", 2), ("auc@5", "AUC@5", 3),
        ("auc@10", "AUC@10", 3), ("auc@20", "AUC@20", 3), ("focal_error_pct", "focal err %", 1),
        ("depth_absrel", "AbsRel", 3), ("depth_delta1", "δ<1.25", 3), ("time_s", "time s", 2),
    )  # fmt: skip
    out = ["| split | method | cases | targets | " + " | ".join(h for _, h, _ in views) + " |"]
    out.append("|---|---|---:|---:|" + "---:|" * len(views))
    for r in rows:
        cells = [r["split"], r["method"], str(r["cases"]), str(r.get("targets", "–"))]
        out.append("| " + " | ".join(cells + [format_cell(r.get(k), d) for k, _, d in views]) + " |")
    out += ["", "| split | ok / cases | " + " | ".join(h for _, h, _ in geo) + " |"]
    out.append("|---|---:|" + "---:|" * len(geo))
    for r in rows:
        if "failed" in r:
            cells = [r["split"], f"{r['cases'] - r['failed']} / {r['cases']}"]
            out.append("| " + " | ".join(cells + [format_cell(r.get(k), d) for k, _, d in geo]) + " |")
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------------------------ files
CSV_COLUMNS = (
    "scene", "split", "context_0", "context_1", "target", "target_name", "method", "status",
    "psnr", "ssim", "psnr_masked", "ssim_masked", "lpips", "mask_fraction", "alpha_coverage",
    "rotation_error_deg", "translation_error_deg", "pose_error_deg", "focal_error_pct_0", "focal_error_pct_1",
    "depth_absrel", "depth_delta1", "time_s", "error",
)  # fmt: skip


def csv_rows(run: EvalRun) -> list[dict[str, Any]]:
    """One row per (case, target, method); case-level fields on the reconstruction's rows."""
    rows = []
    methods = [run.method, *run.config.baselines]
    for r in run.results:
        c = r.case
        base = {"scene": c.scene, "split": c.split, "context_0": c.context[0], "context_1": c.context[1]}
        case_fields = {
            "status": r.status,
            "rotation_error_deg": r.rotation_error_deg,
            "translation_error_deg": r.translation_error_deg,
            "pose_error_deg": r.pose_error_deg,
            "focal_error_pct_0": r.focal_error_pct[0],
            "focal_error_pct_1": r.focal_error_pct[1],
            "depth_absrel": r.depth.get("absrel"),
            "depth_delta1": r.depth.get("delta1"),
            "time_s": r.time_s,
            "error": r.error,
        }
        if not r.targets:
            rows.append({**base, "method": run.method, **case_fields})
        for t in r.targets:
            for m in methods:
                metrics = t.metrics.get(m)
                if m != run.method and metrics is None:
                    continue
                row = {**base, "target": t.index, "target_name": t.name, "method": m}
                row.update(case_fields if m == run.method else {"status": r.status if m == "points" else "ok"})
                row.update({k: v for k, v in (metrics or {}).items() if k in CSV_COLUMNS})
                rows.append(row)
    return rows


def _fmt_csv(v: Any) -> Any:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


class ResultWriter:
    """Writes a run's results into a folder after every case.

    Files: ``cases.jsonl`` (one JSON line per finished case), ``results.json`` (settings, summary
    and every case), ``results.csv`` (one row per case, target and method) and ``summary.md`` (the
    summary tables), each rewritten atomically after every case, and ``coverage/<scene>.json``
    when coverage matrices are given.

    ``cases.jsonl`` is rewritten whole rather than appended to: O(cases) per case, as for
    ``results.json`` (which holds the same cases), and in exchange the file is whole at every
    moment (a run killed mid-write leaves no half line) and is never opened in place, so a
    symbolic link or device planted at its name is refused like at any output (:mod:`.._atomic`)
    instead of being written through. ``coverage/`` may not be a link either.
    """

    FILES = ("cases.jsonl", "results.json", "results.csv", "summary.md")
    """The files written into the folder (besides ``coverage/``)."""

    def __init__(self, folder: str | Path, extra: dict[str, Any] | None = None) -> None:
        self.folder = Path(folder)
        self.extra = extra or {}
        self.check(self.folder)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputPathError(f"cannot create {self.folder}: {e.strerror or e}") from None
        self.jsonl = self.folder / "cases.jsonl"
        self.json_path = self.folder / "results.json"
        self.csv_path = self.folder / "results.csv"

    @classmethod
    def check(cls, folder: str | Path) -> None:
        """Before any work: every file of :attr:`FILES` can be written (:func:`~.._atomic.check_writable`: no
        link, device or folder at its name) and ``coverage/`` is not a link or a file.

        Raises:
            OutputPathError: naming the file.
        """
        folder = Path(folder)
        for name in cls.FILES:
            check_writable(folder / name)
        check_folder(folder / "coverage")

    def write_coverage(self, coverage: dict[str, np.ndarray], frames: dict[str, list[str]]) -> None:
        for scene, cov in coverage.items():
            doc = {"scene": scene, "frames": frames.get(scene, []), "coverage": np.round(cov, 5).tolist()}
            name = scene.replace("/", "_").replace("\\", "_")  # one file directly in coverage/
            atomic_write_text(check_folder(self.folder / "coverage") / f"{name}.json", json.dumps(doc) + "\n")

    def start(self, run: EvalRun) -> None:
        self.write(run)

    def add(self, run: EvalRun, result: CaseResult) -> None:
        self.write(run)

    def write(self, run: EvalRun) -> None:
        from dataclasses import asdict, replace

        cases = [r.to_dict() for r in run.results]
        atomic_write_text(self.jsonl, "".join(json.dumps(c) + "\n" for c in cases))
        doc = {
            "dataset": run.dataset,
            "layout": run.layout,
            "method": run.method,
            "config": to_jsonable({**asdict(replace(run.config, lpips=None)), "lpips": run.config.lpips is not None}),
            **to_jsonable(self.extra),
            "complete": run.complete,
            "cases_total": len(run.cases),
            "cases_done": len(run.results),
            "pending": [c.key for c in run.cases[len(run.results) :]],
            "errors": [{"case": r.case.key, "error": r.error} for r in run.errors],
            "summary": to_jsonable(summarize(run)),
            "cases": cases,
        }
        atomic_write_text(self.json_path, json.dumps(doc, indent=1) + "\n")
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for row in csv_rows(run):
            w.writerow({k: _fmt_csv(v) for k, v in row.items()})
        atomic_write_text(self.csv_path, buf.getvalue())
        atomic_write_text(self.folder / "summary.md", summary_markdown(doc["summary"]))
