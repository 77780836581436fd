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
  coloured points as opaque discs) and ``copy`` (the nearest context photo);
* wall time of the reconstruction (refinement included).

**More than two context views** (``--context-views``, the contexts chosen by :mod:`.contexts`): the
reconstructor gets every context photo; the case records which of them were registered (an unregistered
context is reported with its reason, not fatal; fewer than two registered is the reconstruction's refusal, a
failure as above). Then, by :mod:`.alignment`:

* pose: the rotation and translation-direction errors of every registered context pair's relative pose, their
  means as the case's errors (gauge-free: the reconstruction's frame and scale do not enter), each pair's in
  ``pairs``; focal errors per registered view;
* frame: the similarity taking the reconstruction's frame onto the data set's, fitted on the registered cameras
  (its scale is ``s``: depth is scaled by it as above); every target is rendered from its true camera carried
  into the reconstruction's frame by it, the focal lengths multiplied by the first registered view's
  estimated-to-true ratio;
* the visibility mask is the target's against all the context views, the ``copy`` baseline the nearest of them.

A :class:`~macsplat_cli.errors.ReconstructionError` makes the case a **failure**: it stays
in the results, counts as a 180° pose error in the AUC, and has no image metrics (the copy
baseline is still measured). Bad input met during a case (an unreadable image) makes it
an **error**: recorded with its message, left out of every statistic, and the run goes on.

**A run** (:func:`evaluate`) first checks every case's context views against the pipeline's
minimum photo size (:func:`check_context_sizes`, from the cameras, whose sizes the data set's
loader matched to the image headers: no pixel is read), so such bad input stops the run before
the first reconstruction; then it evaluates the cases in order. With a :class:`~.result_files.ResultWriter`,
``cases.jsonl``, ``results.json`` and ``results.csv`` are rewritten (atomically) after every case,
so an interrupted run keeps everything it finished.

The summary and its tables are :mod:`.summary`'s, the files :mod:`.result_files`'; the settings and result
types are in :mod:`.results`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch

from ..cameras import Camera
from ..datasets import EvalDataset, EvalScene, resize_depth_nearest
from ..datasets.coverage import visibility_mask
from ..errors import DatasetError, InputError, ReconstructionError
from ..metrics import rotation_error_deg, translation_direction_error_deg
from ..pipeline.run import Reconstruction
from ..pipeline.views import MIN_IMAGE_SIDE, working_size
from ..render import render_camera
from .alignment import aligned_camera, fit_similarity, pairwise_pose_errors
from .baselines import nearest_context, point_cloud, render_points
from .metrics import depth_metrics, image_metrics
from .reconstructors import Reconstructor
from .result_files import ResultWriter
from .results import CaseResult, EvalConfig, EvalRun, TargetResult
from .splits import EvalCase
from .summary import known_mean

__all__ = ["check_context_sizes", "evaluate", "evaluate_case", "registered_contexts", "target_camera"]

logger = logging.getLogger(__name__)


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


_Target = tuple[TargetResult, np.ndarray, np.ndarray | None]
"""A target's result (filled as measured), its photo at the compared size [H, W, 3] and its visibility mask [H, W]
bool (None: no depth)."""


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
    gt = [scene.frames[c].camera for c in case.context]
    res = CaseResult(case, reconstructor.name, focal_error_pct=[None] * len(case.context))
    targets, has_depth = _targets_truth(scene, case, cfg)  # independent of the reconstruction
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

    if len(case.context) > 2 or rec.multiview is not None:  # the views registered together, not a pair
        try:
            _measure_views(res, rec, targets, scene, gt, has_depth, cfg)
        except ReconstructionError as e:
            res.status, res.error = "failed", " ".join(str(e).split())
        return res
    ratios = _measure_pose(res, rec, gt)
    res.registered = list(case.context)
    if has_depth and rec.depths:
        _measure_depth(res, rec, scene, list(case.context))
    scale, ratio0 = res.scale, ratios[0]

    def place(target: Camera, width: int, height: int) -> Camera:
        return target_camera(target, gt[0], scale=scale, width=width, height=height, focal_ratio=ratio0)

    _measure_targets(res, rec, targets, scene, place, cfg)
    return res


def _targets_truth(scene: EvalScene, case: EvalCase, cfg: EvalConfig) -> tuple[list[_Target], bool]:
    """The ground truth of every target (photo, visibility mask) and the copy baseline's metrics; whether both
    context views have depth."""
    size = cfg.eval_size or cfg.settings.size
    frames = scene.frames
    gt = [frames[c].camera for c in case.context]
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
            near = case.context[nearest_context(frames[ti].camera, gt)]
            tr.metrics["copy"] = image_metrics(
                photo(near, wh), image, mask, splatt3r=cfg.splatt3r_compatible, lpips=cfg.lpips
            )
        targets.append((tr, image, mask))
    return targets, has_depth


def _measure_pose(res: CaseResult, rec: Reconstruction, gt: list[Camera]) -> list[tuple[float, float]]:
    """Pose errors, the scale ``s`` and the focal errors into ``res``; the (fx, fy) estimated-to-true focal ratio
    of each context view."""
    T_gt = gt[1].world_to_cam @ gt[0].cam_to_world
    if rec.pose is not None:  # the pair's relative pose, as the pose stage estimated it
        R, t = rec.pose.geometry.R, rec.pose.geometry.t
    else:  # a reconstruction given its cameras: camera 1's pose in camera 0's frame
        T = np.linalg.inv(rec.poses[1]) @ rec.poses[0]
        R, t = T[:3, :3], T[:3, 3]
    res.rotation_error_deg = rotation_error_deg(R, T_gt[:3, :3])
    res.translation_error_deg = translation_direction_error_deg(t, T_gt[:3, 3])
    t_est = float(np.linalg.norm(t))
    res.scale = float(np.linalg.norm(T_gt[:3, 3])) / t_est if rec.scale == "relative" and t_est > 0 else 1.0
    K_est = (rec.views[0].K, rec.views[1].K)
    ratios = []
    for k, v in enumerate(rec.views):
        K_true = gt[k].rescaled(v.width, v.height).K
        ratios.append((K_est[k][0, 0] / K_true[0, 0], K_est[k][1, 1] / K_true[1, 1]))
        if v.intrinsics_source != "file":
            res.focal_error_pct[k] = 100.0 * (ratios[k][0] - 1.0)
    return ratios


def _measure_depth(res: CaseResult, rec: Reconstruction, scene: EvalScene, frames: list[int]) -> None:
    """Depth metrics of the context views' depth maps (at their own size, scaled by ``res.scale``) into ``res``;
    ``frames``: each depth map's frame index."""
    per_view = []
    for k, dm in enumerate(rec.depths):
        h, w = dm.depth.shape
        depth = scene.depth(frames[k])
        if depth is None:  # pragma: no cover - measured only for a scene with depth (has_depth)
            raise ReconstructionError(f"frame {frames[k]} has no depth to measure against")
        d_true = _resize_to(depth, w, h)
        est = np.where(dm.valid, dm.depth, 0.0)
        per_view.append(depth_metrics(est, d_true, res.scale))
    res.depth = {key: known_mean([m[key] for m in per_view]) for key in per_view[0]}


def _measure_targets(
    res: CaseResult,
    rec: Reconstruction,
    targets: list[_Target],
    scene: EvalScene,
    place: Callable[[Camera, int, int], Camera],
    cfg: EvalConfig,
) -> None:
    """Render every target from its true camera in the reconstruction's frame (``place``: the true camera, width,
    height → the camera in that frame); its metrics (and the points baseline's) into its :class:`TargetResult`."""
    points = point_cloud(rec.gaussians, cfg.points) if "points" in cfg.baselines else None
    for tr, image, mask in targets:
        cam = place(scene.frames[tr.index].camera, tr.size[0], tr.size[1])
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


# ------------------------------------------------------------------------------------ more than two contexts
def registered_contexts(rec: Reconstruction, stems: list[str]) -> tuple[list[int], dict[int, str]]:
    """Which context photos a reconstruction of more than two registered.

    Read from the report's ``multiview`` photos (every input photo in input order, ``registered`` or not, with
    the reason); without them, by the views' names (the photos' stems), in order.

    Args:
        rec: the reconstruction.
        stems: the context photos' file stems, in the order the reconstruction got them.

    Returns:
        The position in the context of each of ``rec.views``, and the reason of each context position left out.

    Raises:
        ReconstructionError: the views cannot be matched to the context photos.
    """
    photos = (rec.report.multiview or {}).get("photos")
    pos: list[int] = []
    if photos is not None and len(photos) == len(stems):
        pos = [k for k, p in enumerate(photos) if p.get("registered")]
        reasons = {k: str(p.get("reason") or "not registered") for k, p in enumerate(photos) if not p.get("registered")}
    else:
        for v in rec.views:
            pos.append(next((k for k in range(len(stems)) if k not in pos and stems[k] == v.name), -1))
        reasons = {k: "not registered" for k in range(len(stems)) if k not in pos}
    if len(pos) != len(rec.views) or -1 in pos or len(pos) < 2:
        raise ReconstructionError("the reconstruction's views cannot be matched to the context photos")
    return pos, reasons


def _measure_views(
    res: CaseResult,
    rec: Reconstruction,
    targets: list[_Target],
    scene: EvalScene,
    gt: list[Camera],
    has_depth: bool,
    cfg: EvalConfig,
) -> None:
    """More than two context views (module docstring): registration, pair errors, the similarity onto the truth,
    focal and depth errors, the targets rendered through it; into ``res``."""
    case = res.case
    pos, reasons = registered_contexts(rec, [scene.frames[c].image.stem for c in case.context])
    res.registered = [case.context[k] for k in pos]
    res.unregistered = [
        {"frame": case.context[k], "name": scene.frames[case.context[k]].name, "reason": why}
        for k, why in sorted(reasons.items())
    ]
    est = np.stack([np.asarray(T, np.float64) for T in rec.poses])  # [M, 4, 4]
    true = np.stack([gt[k].cam_to_world for k in pos])
    errors = pairwise_pose_errors(est, true, pos)
    res.pairs = [
        {"context": [case.context[e.i], case.context[e.j]], "rotation_error_deg": e.rotation_deg,
         "translation_error_deg": e.translation_deg}
        for e in errors
    ]  # fmt: skip
    res.rotation_error_deg = float(np.mean([e.rotation_deg for e in errors]))
    res.translation_error_deg = float(np.mean([e.translation_deg for e in errors]))
    sim = fit_similarity(est, true, fix_scale=rec.scale != "relative")
    res.scale = sim.scale
    ratios = []
    for j, (v, k) in enumerate(zip(rec.views, pos)):
        K_true = gt[k].rescaled(v.width, v.height).K
        ratios.append((v.K[0, 0] / K_true[0, 0], v.K[1, 1] / K_true[1, 1]))
        if v.intrinsics_source != "file":
            res.focal_error_pct[k] = 100.0 * (ratios[j][0] - 1.0)
    if has_depth and len(rec.depths) == len(rec.views):
        _measure_depth(res, rec, scene, res.registered)

    def place(target: Camera, width: int, height: int) -> Camera:
        return aligned_camera(target, sim, width=width, height=height, focal_ratio=ratios[0])

    _measure_targets(res, rec, targets, scene, place, cfg)


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
