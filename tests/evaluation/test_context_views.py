"""More than two context views per case: which frames are added, the gauge-free pose errors, the frame alignment,
and the protocol on a three-view case.

Data are generated: cameras along a line (``support.evaluation.translated_camera``; the between test and the
distances are hand-computable), the smoothly textured plane data set of ``support.evaluation``, and random rigs.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.errors import DatasetError, InputError
from macsplat_cli.evaluation import (
    CaseResult,
    EvalCase,
    EvalConfig,
    OracleReconstructor,
    ReconstructSettings,
    SplitConfig,
    evaluate_case,
    load_dataset,
    make_cases,
)
from macsplat_cli.evaluation.alignment import Similarity, aligned_camera, fit_similarity, pairwise_pose_errors
from macsplat_cli.evaluation.baselines import nearest_context
from macsplat_cli.evaluation.contexts import check_context_views, extend_case, extend_cases
from macsplat_cli.evaluation.splits import load_cases
from macsplat_cli.pipeline.gaussian_init import view_gaussians
from macsplat_cli.pipeline.run import Reconstruction
from macsplat_cli.pipeline.types import DepthMap

from support.evaluation import ORACLE, PLANE_X, translated_camera


def _line(n: int = 11, step: float = 0.1) -> list[Camera]:
    return [translated_camera(f"v{i}", step * i) for i in range(n)]


# ------------------------------------------------------------------------------------ which frames are added
def test_contexts_spread_between_the_pair_then_around_it() -> None:
    """Eleven cameras 0.1 apart on a line: the farthest-point order and the around order are hand-computable."""
    cams = _line()
    case = EvalCase("s", "x", (0, 10), (3, 7))
    # between: the midpoint (5) first; then 2 and 8 are both 0.2 from their nearest context: the lower index
    got = extend_case(cams, case, 4)
    assert got is not None and got.context == (0, 2, 5, 10) and got.pair == (0, 10) and got.targets == (3, 7)
    assert extend_case(cams, case, 3).context == (0, 5, 10)  # type: ignore[union-attr]
    # nothing between (4 is a target): the frames nearest to the segment, 2 and 6 (0.1 each, 2 first), in path order
    around = extend_case([*cams, translated_camera("dup", 0.3)], EvalCase("s", "x", (3, 5), (4,)), 4)
    assert around is not None and around.context == (2, 3, 5, 6)  # "dup" (frame 11) is at frame 3: no baseline
    assert around.key == "s/x/2-3-5-6"
    assert extend_case(cams[:6], EvalCase("s", "x", (0, 5), (1, 2, 3, 4)), 3) is None  # every other frame a target
    assert extend_case(cams, case, 2) is case  # two context views: the case as drawn


def test_extended_cases_keep_the_pairs_and_targets_of_two_views(plane: Path) -> None:
    ds = load_dataset(plane)
    two = make_cases(ds, SplitConfig(max_pairs=None, max_targets=None)).cases
    three, left = extend_cases(ds, two, 3)
    assert len(three) + len(left) == len(two) and three and left
    kept = iter(three)
    for case in two:
        if case in left:  # every frame of the scene is a context or a target
            assert len(PLANE_X) - 2 - len(case.targets) < 1
            continue
        ext = next(kept)
        assert ext.pair == case.context and ext.targets == case.targets and ext.split == case.split
        assert len(ext.context) == len(set(ext.context)) == 3 and set(case.context) < set(ext.context)
        assert not set(ext.context) & set(ext.targets)
        xs = [PLANE_X[c] for c in ext.context]
        assert xs == sorted(xs)  # path order along the pair's segment
        assert ext.to_dict()["context_views"] == 3 and ext.to_dict()["pair"] == list(case.context)
    assert extend_cases(ds, two, 2) == (two, [])


def test_cases_file_with_more_contexts(plane: Path, tmp_path: Path) -> None:
    ds = load_dataset(plane)
    f = tmp_path / "cases.json"
    f.write_text(json.dumps({"cases": [{"split": "mine", "context": [0, 2, 4], "targets": [1, 3]}]}))
    (case,) = load_cases(f, ds).cases
    assert case.context == (0, 2, 4) and case.key == "plane/mine/0-2-4"
    assert extend_cases(ds, [case], 3) == ([case], [])
    with pytest.raises(DatasetError, match="0-2-4 has 3 context frames and --context-views is 2: pass --context-v"):
        extend_cases(ds, [case], 2)
    with pytest.raises(DatasetError, match="is 4: give cases of two context frames \\(extended to 4\\) or 4"):
        extend_cases(ds, [case], 4)
    f.write_text(json.dumps({"cases": [{"split": "mine", "context": [0, 2, 0], "targets": [1]}]}))
    with pytest.raises(DatasetError, match="the context frames of plane/mine/0-2-0 repeat a frame"):
        load_cases(f, ds)


def test_bad_context_view_counts() -> None:
    for bad in (1, 0, -3, 65, True):
        with pytest.raises(InputError, match="--context-views .*: give 2 to 64"):
            check_context_views(bad)  # type: ignore[arg-type]
    check_context_views(2, backends=["neural"])  # two views: today's protocol
    check_context_views(64)
    with pytest.raises(InputError, match="neural backend reconstructs two photos"):
        check_context_views(3, backends=["classical", "neural"])


def test_nearest_context_of_many() -> None:
    cams = [translated_camera(f"c{i}", x) for i, x in enumerate((0.0, 1.0, 0.5))]
    assert nearest_context(translated_camera("t", 0.6), cams) == 2
    assert nearest_context(translated_camera("t", 0.25), cams[:2]) == 0  # two: as before
    assert nearest_context(translated_camera("t", 0.75), cams) == 1  # a tie at 0.25: the first of 1 and 2


# ------------------------------------------------------------------------------------ gauge-free measures
def _random_rig(rng: np.random.Generator, n: int, collinear: bool = False) -> np.ndarray:
    """``n`` cameras' cam_to_world [n, 4, 4]: random orientations, centres random or on one line."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        T[k, :3, :3] = S.rotation_about(rng.normal(size=3), float(rng.uniform(5, 60)))
        T[k, :3, 3] = np.array([0.4 * k, 0.0, 0.0]) if collinear else rng.normal(size=3)
    return T


def _similarity(rng: np.random.Generator) -> Similarity:
    return Similarity(float(rng.uniform(0.2, 5.0)), S.rotation_about(rng.normal(size=3), 70.0), rng.normal(size=3))


def test_pose_errors_are_gauge_free() -> None:
    """A similarity applied to the estimated cameras leaves every pair's errors unchanged."""
    rng = np.random.default_rng(3)
    true = _random_rig(rng, 4)
    est = true.copy()
    est[2, :3, :3] = S.rotation_about((0.2, 1.0, 0.1), 3.0) @ est[2, :3, :3]  # one camera turned by 3°
    est[3, :3, 3] += 0.05 * rng.normal(size=3)  # one moved
    base = pairwise_pose_errors(est, true)
    assert len(base) == 6 and max(e.rotation_deg for e in base) == pytest.approx(3.0, abs=1e-9)
    assert all(e.rotation_deg < 1e-9 for e in base if 2 not in (e.i, e.j))
    for _ in range(3):
        moved = pairwise_pose_errors(_similarity(rng).apply_to_cameras(est), true)
        for a, b in zip(base, moved):
            assert (a.i, a.j) == (b.i, b.j)
            assert b.rotation_deg == pytest.approx(a.rotation_deg, abs=1e-9)
            assert b.translation_deg == pytest.approx(a.translation_deg, abs=1e-9)


@pytest.mark.parametrize("collinear", [False, True])
def test_similarity_fit_recovers_the_gauge(collinear: bool) -> None:
    """Exact cameras in another frame: the fit finds it (orientations fix the rotation about a line of centres);
    on perturbed cameras, the aligned target camera does not depend on the frame."""
    rng = np.random.default_rng(7)
    true = _random_rig(rng, 3, collinear)
    g = _similarity(rng)
    inv = Similarity(1.0 / g.scale, g.Q.T, -g.Q.T @ g.T / g.scale)
    est = inv.apply_to_cameras(true)
    fit = fit_similarity(est, true, fix_scale=False)
    assert fit.scale == pytest.approx(g.scale, rel=1e-9)
    assert np.abs(fit.Q - g.Q).max() < 1e-9 and np.abs(fit.T - g.T).max() < 1e-9
    assert np.abs(fit.apply_to_cameras(est) - true).max() < 1e-9
    est[1, :3, 3] += 0.03 * rng.normal(size=3)
    target = Camera("t", 96, 64, S.intrinsics(96, 64, 60.0), _random_rig(rng, 1)[0])
    fit = fit_similarity(est, true, fix_scale=False)
    cam = aligned_camera(target, fit, width=96, height=64, focal_ratio=(1.0, 1.0))
    h = _similarity(rng)
    fit_h = fit_similarity(h.apply_to_cameras(est), true, fix_scale=False)
    cam_h = aligned_camera(target, fit_h, width=96, height=64, focal_ratio=(1.0, 1.0))
    assert np.abs(h.apply_to_cameras(cam.cam_to_world[None])[0] - cam_h.cam_to_world).max() < 1e-9


# ------------------------------------------------------------------------------------ the protocol
class _Gauge:
    """The oracle's three-view reconstruction in another frame (``similarity``) with context ``turn`` turned by
    2°, or with context ``drop`` left unregistered."""

    name = "oracle"

    def __init__(self, similarity: Similarity | None = None, turn: int | None = None, drop: int | None = None):
        self.sim, self.turn, self.drop = similarity, turn, drop

    def __call__(self, scene, case, settings) -> Reconstruction:  # noqa: ANN001
        rec = ORACLE(scene, case, settings)
        keep = [k for k in range(len(rec.views)) if k != self.drop]
        poses = np.stack([rec.poses[k] for k in keep])
        if self.turn is not None:
            poses[self.turn, :3, :3] = poses[self.turn, :3, :3] @ S.rotation_about((0, 1, 0), 2.0)
        s = 1.0
        if self.sim is not None:
            poses, s = self.sim.apply_to_cameras(poses), self.sim.scale
        views = [rec.views[k] for k in keep]
        depths = [DepthMap(rec.depths[k].depth * np.float32(s), rec.depths[k].confidence) for k in keep]
        maps = [view_gaussians(v, d, v.K, P, ORACLE.gaussians) for v, d, P in zip(views, depths, poses)]
        photos = [{"name": v.name, "registered": k != self.drop} for k, v in enumerate(rec.views)]
        if self.drop is not None:
            photos[self.drop]["reason"] = "PnP found 3 inliers"
        report = dataclasses.replace(rec.report, multiview={"photos": photos})
        return Reconstruction(views, list(poses), depths, maps, report, scale="relative")


def _evaluate(plane: Path, reconstructor: object) -> CaseResult:
    ds = load_dataset(plane)
    case = EvalCase("plane", "x", (0, 2, 4), (1, 3), pair=(0, 4))
    return evaluate_case(ds.scenes[0], case, reconstructor, EvalConfig(settings=ReconstructSettings(size=96)))  # type: ignore[arg-type]


def test_three_context_views_measured_in_any_frame(plane: Path) -> None:
    """Ground truth: no pose error, the scale and depth of the relative frame, ≥ 40 dB; a perturbed estimate
    measures the same in any frame."""
    r = _evaluate(plane, OracleReconstructor(scale="relative", gaussians=ORACLE.gaussians))
    assert r.status == "ok" and r.registered == [0, 2, 4] and r.unregistered == [] and len(r.pairs) == 3
    assert r.rotation_error_deg < 1e-6 and r.translation_error_deg < 1e-6
    assert r.scale == pytest.approx(PLANE_X[2], rel=1e-9)  # the oracle's unit: the first two contexts' baseline
    assert r.depth["absrel"] < 1e-5 and r.focal_error_pct == [None, None, None]
    for t in r.targets:
        assert t.metrics["oracle"]["psnr"] >= 40.0 and t.metrics["oracle"]["psnr_masked"] >= 40.0
    assert r.to_dict()["registered"] == 3 and r.to_dict()["context_views"] == 3
    turned = _evaluate(plane, _Gauge(turn=1))
    assert turned.rotation_error_deg == pytest.approx(2 * 2.0 / 3, abs=1e-9)  # two of three pairs off by 2°
    g = _similarity(np.random.default_rng(5))
    moved = _evaluate(plane, _Gauge(g, turn=1))
    assert moved.rotation_error_deg == pytest.approx(turned.rotation_error_deg, abs=1e-9)
    assert moved.translation_error_deg == pytest.approx(turned.translation_error_deg, abs=1e-9)
    assert moved.scale * g.scale == pytest.approx(turned.scale, rel=1e-9)
    # the images: the plane's Gaussians from three views coincide, so their compositing order follows the
    # rounding of their depths; a similarity that keeps every depth's arithmetic exact (a turn about the optical
    # axis, a power-of-two scale, a shift across it) must render the same image to float32 rounding
    exact = Similarity(2.0, S.rotation_about((0, 0, 1), 40.0), np.array([0.5, -0.25, 0.0]))
    across = _evaluate(plane, _Gauge(exact, turn=1))
    assert across.rotation_error_deg == pytest.approx(turned.rotation_error_deg, abs=1e-9)
    for a, b in zip(turned.targets, across.targets):
        assert b.metrics["oracle"]["psnr"] == pytest.approx(a.metrics["oracle"]["psnr"], abs=1e-3)


def test_an_unregistered_context_is_reported_not_fatal(plane: Path) -> None:
    r = _evaluate(plane, _Gauge(drop=1))
    assert r.status == "ok" and r.registered == [0, 4] and len(r.pairs) == 1
    assert r.unregistered == [{"frame": 2, "name": "f2", "reason": "PnP found 3 inliers"}]
    assert r.rotation_error_deg < 1e-6 and r.to_dict()["registered"] == 2
    assert all(t.metrics["oracle"]["psnr"] >= 40.0 for t in r.targets)  # two registered views still align
