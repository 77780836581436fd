"""The evaluation library: loaders, coverage and splits, metrics, baselines, the protocol, the bench.

Data are generated: a smoothly textured plane seen by cameras translated along x (so coverage and
the visibility mask have closed forms; ``support.evaluation``, shared with ``test_cli_eval.py``), and
here hand-built camera rigs and small synthetic ScanNet++ / ICL-NUIM trees.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import nerfstudio_to_opencv, opencv_to_nerfstudio
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.datasets.coverage import coverage_matrix, visibility_mask
from macsplat_cli.errors import DatasetError, ReconstructionError
from macsplat_cli.evaluation import (
    EvalCase,
    EvalConfig,
    OracleReconstructor,
    PointsConfig,
    ReconstructSettings,
    ResultWriter,
    SplitConfig,
    evaluate,
    evaluate_case,
    load_dataset,
    make_cases,
    summarize,
)
from macsplat_cli.evaluation.baselines import PointCloud, nearest_context, render_points
from macsplat_cli.evaluation.bench import (
    BenchRow,
    BenchSetting,
    bench_markdown,
    grid,
    pareto_front,
    run_bench,
)
from macsplat_cli.evaluation.metrics import depth_metrics, image_metrics, pose_auc
from macsplat_cli.evaluation.protocol import target_camera
from macsplat_cli.evaluation.reconstructors import BACKENDS
from macsplat_cli.evaluation.splits import COVERAGE_THRESHOLDS, angle_splits, coverage_splits, load_cases
from macsplat_cli.images import save_depth, save_image
from macsplat_cli.metrics import (
    angle_between_deg,
    rotation_angle_deg,
    rotation_error_deg,
    ssim,
    translation_direction_error_deg,
)
from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig

from support.evaluation import (
    ORACLE,
    PLANE_X,
    H,
    K,
    W,
    Z,
    translated_camera,
    write_blank_dataset,
    write_plane_dataset,
)


def plane_coverage(xa: float, xb: float) -> float:
    """Fraction of b's pixels inside a's image for the fronto-parallel plane at depth Z."""
    return 1.0 - abs(xb - xa) * K[0, 0] / Z / W


# ------------------------------------------------------------------------------------ loaders
def test_generic_loader_reads_what_write_dataset_writes(plane: Path) -> None:
    ds = load_dataset(plane)
    assert ds.layout == "generic" and len(ds.scenes) == 1
    scene = ds.scenes[0]
    assert scene.scale == "metric" and scene.has_depth
    assert [f.name for f in scene.frames] == [f"f{i}" for i in range(len(PLANE_X))]
    assert np.allclose(scene.frames[3].camera.center, [PLANE_X[3], 0, 0])
    d = scene.depth(0)
    assert d.shape == (H, W) and np.allclose(d, Z, atol=1e-3)  # 16-bit PNG in mm, a plane at 3 m
    assert scene.depth(0, (48, 32)).shape == (32, 48)
    assert scene.rgb(1, (48, 32)).shape == (32, 48, 3)


def test_bad_datasets_name_the_file(tmp_path: Path) -> None:
    cams = [translated_camera(f"v{i}", 0.1 * i) for i in range(3)]
    root = tmp_path / "a"
    write_blank_dataset(root, cams)
    (root / "images" / "v1.png").unlink()
    with pytest.raises(DatasetError, match=r"images/v1: image not found \(looked for v1\.\*"):
        load_dataset(root)
    save_image(root / "images" / "v1.png", np.zeros((H + 2, W, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"v1\.png: the image is 96x66, but its camera 'v1' is 96x64"):
        load_dataset(root)
    (root / "images" / "v1.png").write_bytes(b"not an image")
    with pytest.raises(DatasetError, match=r"v1\.png: not a readable image"):
        load_dataset(root)
    (root / "cameras.json").write_text("{", encoding="utf-8")
    with pytest.raises(DatasetError, match=r"cameras\.json: invalid JSON"):
        load_dataset(root)
    with pytest.raises(DatasetError, match="no such folder"):
        load_dataset(tmp_path / "missing")
    with pytest.raises(DatasetError, match="not a data set folder"):
        load_dataset(tmp_path / "a" / "images")


def test_scannetpp_loader_converts_poses_and_filters_frames(tmp_path: Path) -> None:
    """A synthetic ScanNet++ release tree (reference notes §4.6): nerfstudio poses, is_bad, depth in mm."""
    root = tmp_path / "scannetpp"
    (root / "splits").mkdir(parents=True)
    (root / "splits" / "nvs_sem_val.txt").write_text("abc123\nnot_downloaded\n")
    dslr = root / "data" / "abc123" / "dslr"
    (dslr / "resized_undistorted_images").mkdir(parents=True)
    (dslr / "undistorted_depths").mkdir()
    (dslr / "nerfstudio").mkdir()
    rng = np.random.default_rng(0)
    cams, frames = [], []
    for i in range(5):
        T = np.eye(4)
        T[:3, :3] = S.rotation_about(rng.normal(size=3), float(rng.uniform(0, 40)))
        T[:3, 3] = rng.normal(size=3)
        name = f"DSC{i:05d}.JPG"
        cams.append(T)
        frames.append({"file_path": name, "transform_matrix": opencv_to_nerfstudio(T).tolist(), "is_bad": i == 2})
        if i != 4:  # a withheld test image
            save_image(dslr / "resized_undistorted_images" / name, np.full((48, 64, 3), 100, np.uint8))
            save_depth(dslr / "undistorted_depths" / f"DSC{i:05d}.png", np.full((48, 64), 1.5 + i, np.float32))
    tu = {"w": 64, "h": 48, "fl_x": 50.0, "fl_y": 51.0, "cx": 32.0, "cy": 24.0, "frames": frames[:4]}
    tu["test_frames"] = frames[4:]
    (dslr / "nerfstudio" / "transforms_undistorted.json").write_text(json.dumps(tu))
    names = [f["file_path"] for f in frames]
    (dslr / "train_test_lists.json").write_text(json.dumps({"train": names[:4], "test": names[4:]}))

    ds = load_dataset(root)
    assert ds.layout == "scannetpp"
    scene = ds.scene("abc123")
    assert [f.name for f in scene.frames] == ["DSC00000", "DSC00001", "DSC00003"]  # is_bad dropped
    for f, i in zip(scene.frames, (0, 1, 3)):
        assert np.abs(f.camera.cam_to_world - cams[i]).max() < 1e-12  # the pose round trip
        assert f.camera.K[0, 0] == 50.0 and f.camera.K[1, 1] == 51.0
    assert np.allclose(scene.depth(2), 4.5)  # uint16 mm
    T = np.array(frames[0]["transform_matrix"])
    assert np.abs(nerfstudio_to_opencv(opencv_to_nerfstudio(T)) - T).max() < 1e-12


def test_icl_nuim_loader_makes_a_right_handed_rig(tmp_path: Path) -> None:
    root = tmp_path / "icl"
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = []
    for i in range(1, 4):
        save_image(root / "color" / f"{i}.png", np.zeros((480, 640, 3), np.uint8))
        cv2.imwrite(str(root / "depth" / f"{i}.png"), np.full((480, 640), 5000 * i, np.uint16))
        lines.append(f"{0.1 * i} 0.2 0.3 0 0.0871557 0 0.9961947")  # 10° about y
    (root / "pose.txt").write_text("\n".join(lines) + "\n")
    ds = load_dataset(root)
    assert ds.layout == "icl-nuim"
    cam = ds.scenes[0].frames[0].camera
    F = np.diag([1.0, -1.0, 1.0])
    assert cam.K[1, 1] == 480.0 and cam.K[0, 2] == 320.0
    assert np.allclose(cam.cam_to_world[:3, :3], F @ S.rotation_about((0, 1, 0), 10.0) @ F)
    assert np.allclose(cam.center, [0.1, -0.2, 0.3])
    assert np.allclose(ds.scenes[0].depth(1), 2.0)  # value / 5000


# ------------------------------------------------------------------------------------ coverage and splits
def test_visibility_mask_hand_computed() -> None:
    """Target and context 0.1 m apart facing a wall at 2 m: the frustum edge and a depth mismatch."""
    Kc = np.array([[10.0, 0.0, 8.0], [0.0, 10.0, 4.0], [0.0, 0.0, 1.0]])
    target = Camera("t", 16, 8, Kc, np.eye(4))
    ctx_T = np.eye(4)
    ctx_T[0, 3] = 0.4  # shift of 0.4 · 10 / 2 = 2 px: target columns 0, 1 fall outside the context
    ctx = Camera("c", 16, 8, Kc, ctx_T)
    depth = np.full((8, 16), 2.0)
    mask = visibility_mask(depth, target, [depth], [ctx])
    assert (~mask[:, :2]).all() and mask[:, 2:].all()
    occluded = depth.copy()
    occluded[:, :8] = 1.0  # the context sees a nearer surface in its left half: target columns 2..9
    mask = visibility_mask(depth, target, [occluded], [ctx])
    assert mask[:, 10:].all() and not mask[:, :10].any()
    assert not visibility_mask(np.zeros((8, 16)), target, [depth], [ctx]).any()  # no target depth, no pixel
    # OR over contexts: a second context at the target's pose sees everything
    assert visibility_mask(depth, target, [occluded, depth], [ctx, target]).all()


def test_coverage_matrix_matches_the_plane_geometry(plane: Path) -> None:
    scene = load_dataset(plane).scenes[0]
    cov = coverage_matrix(scene)
    n = len(PLANE_X)
    for a, b in itertools.product(range(n), range(n)):
        assert abs(cov[a, b] - max(0.0, plane_coverage(PLANE_X[a], PLANE_X[b]))) <= 1.0 / W + 1e-9, (a, b)


def test_split_assignment_by_coverage(plane: Path) -> None:
    ds = load_dataset(plane)
    sel = make_cases(ds, SplitConfig(max_pairs=None, max_targets=None))
    assert sel.modes == {"plane": "coverage"}
    n = len(PLANE_X)
    expected = {}
    for a, b in itertools.combinations(range(n), 2):
        splits = coverage_splits(plane_coverage(PLANE_X[a], PLANE_X[b]))
        if not splits:
            continue
        psi = COVERAGE_THRESHOLDS[splits[0]][1]
        best = [max(plane_coverage(PLANE_X[f], PLANE_X[a]), plane_coverage(PLANE_X[f], PLANE_X[b])) for f in range(n)]
        targets = tuple(f for f in range(n) if f not in (a, b) and best[f] >= psi)
        if targets:
            expected[(a, b)] = (splits[0], targets)
    got = {c.context: (c.split, c.targets) for c in sel.cases}
    assert got == expected
    assert {s for s, _ in got.values()} == {"close", "medium", "wide", "very-wide"}
    # lower-bound reading: a close pair is a test case of every split
    sel_t = make_cases(ds, SplitConfig(max_pairs=None, max_targets=None, assignment="threshold"))
    close = next(c.context for c in sel.cases if c.split == "close")
    assert {c.split for c in sel_t.cases if c.context == close} == {"close", "medium", "wide", "very-wide"}
    # the draw is seeded and bounded
    sel_1 = make_cases(ds, SplitConfig(max_pairs=1, max_targets=1, splits=("wide",)))
    assert len(sel_1.cases) == 1 and len(sel_1.cases[0].targets) == 1 and sel_1.cases[0].split == "wide"
    assert make_cases(ds, SplitConfig(max_pairs=1, max_targets=1, splits=("wide",))).cases == sel_1.cases


def test_split_assignment_by_view_angle(tmp_path: Path) -> None:
    assert angle_splits(0.0) == ["close"] and angle_splits(15.0) == ["close"] and angle_splits(15.5) == ["medium"]
    assert angle_splits(50.0) == ["wide"] and angle_splits(80.0) == ["very-wide"] and angle_splits(120.0) == []
    assert angle_splits(10.0, "threshold") == ["close", "medium", "wide", "very-wide"]
    assert angle_splits(50.0, "threshold") == ["wide", "very-wide"]
    # cameras on a line, turning: angle between optical axes = yaw difference; targets lie between
    yaws = (0.0, 5.0, 10.0, 30.0, 80.0)
    root = tmp_path / "rig"
    write_blank_dataset(root, [translated_camera(f"v{i}", 0.25 * i, y) for i, y in enumerate(yaws)])
    sel = make_cases(load_dataset(root), SplitConfig(max_pairs=None, max_targets=None))
    assert sel.modes == {"rig": "angle"}
    got = {c.context: (c.split, c.targets) for c in sel.cases}
    assert got == {
        (0, 2): ("close", (1,)),
        (0, 3): ("medium", (1, 2)),
        (1, 3): ("medium", (2,)),
        (0, 4): ("very-wide", (1, 2, 3)),
        (1, 4): ("very-wide", (2, 3)),
        (2, 4): ("very-wide", (3,)),
    }
    with pytest.raises(DatasetError, match="need depth"):
        make_cases(load_dataset(root), SplitConfig(mode="coverage"))


def test_cases_file_formats(plane: Path, tmp_path: Path) -> None:
    ds = load_dataset(plane)
    ours = tmp_path / "cases.json"
    ours.write_text(json.dumps({"cases": [{"split": "mine", "context": [0, 3], "targets": [1, 2]}]}))
    assert [(c.split, c.context, c.targets) for c in load_cases(ours, ds).cases] == [("mine", (0, 3), (1, 2))]
    splatt3r = tmp_path / "test_set_0.7_0.7.json"
    splatt3r.write_text(json.dumps([["plane", 0, 3, 1], ["plane", 0, 3, 2], ["plane", 1, 4, 2]]))
    got = [(c.split, c.context, c.targets) for c in load_cases(splatt3r, ds).cases]
    assert got == [("medium", (0, 3), (1, 2)), ("medium", (1, 4), (2,))]
    splatt3r.write_text(json.dumps([["plane", 0, 3, 9]]))
    with pytest.raises(DatasetError, match="frame index 9 out of range"):
        load_cases(splatt3r, ds)


# ------------------------------------------------------------------------------------ metrics
def test_image_metrics_hand_computed() -> None:
    target = np.full((16, 16, 3), 0.5)
    mask = np.zeros((16, 16), bool)
    mask[:, :8] = True
    pred = target + np.where(mask[..., None], 0.1, 0.2)
    m = image_metrics(pred, target, mask)
    assert m["psnr"] == pytest.approx(-10 * math.log10(0.5 * 0.01 + 0.5 * 0.04))
    assert m["psnr_masked"] == pytest.approx(20.0)  # per-channel MSE 0.01 over the mask
    assert m["mask_fraction"] == 0.5
    s = image_metrics(pred, target, mask, splatt3r=True)
    assert s["psnr"] == pytest.approx(-10 * math.log10(0.5 * 0.01))  # masked-out pixels: zero error
    assert s["psnr_masked"] == pytest.approx(20.0 - 10 * math.log10(3.0))  # the channel-summed −4.77 dB
    assert math.isnan(s["ssim_masked"])
    # SSIM of two constant images: (2ab + C1) / (a² + b² + C1), the structure term is 1
    # (the map is float32: flat images are its worst case, within 1e-3; textured ones within 1e-5)
    c = image_metrics(np.full((16, 16, 3), 0.5), np.full((16, 16, 3), 0.6))
    assert c["ssim"] == pytest.approx((2 * 0.3 + 1e-4) / (0.25 + 0.36 + 1e-4), abs=1e-3)
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(32, 40, 3)), rng.uniform(size=(32, 40, 3))
    b = 0.5 * a + 0.5 * b
    assert image_metrics(a, b)["ssim"] == pytest.approx(ssim(a, b), abs=1e-5)
    assert image_metrics(a, b, np.ones((32, 40), bool))["ssim_masked"] == pytest.approx(ssim(a, b), abs=1e-5)
    assert image_metrics(target, target, mask)["ssim_masked"] == pytest.approx(1.0)


def test_pose_auc_hand_computed() -> None:
    assert pose_auc([1.0, 3.0])["auc@5"] == pytest.approx(0.75)  # trapezoids through (0,0), (1,½), (3,1), (5,1)
    auc = pose_auc([1.0, 3.0, 180.0])  # a failure: 180°
    assert auc["auc@5"] == pytest.approx((1 / 6 + 1 + 4 / 3) / 5)
    assert auc["auc@10"] == pytest.approx((1 / 6 + 1 + 14 / 3) / 10)
    assert pose_auc([0.0, math.nan]) == pose_auc([0.0, 180.0]) == {"auc@5": 0.5, "auc@10": 0.5, "auc@20": 0.5}
    assert math.isnan(pose_auc([])["auc@5"])


def test_depth_metrics_hand_computed() -> None:
    gt = np.array([1.0, 2.0, 4.0, 0.0, 3.0])
    pred = np.array([1.1, 2.0, 2.0, 5.0, 0.0])
    m = depth_metrics(pred, gt)
    assert m["absrel"] == pytest.approx((0.1 + 0.0 + 0.5) / 3)
    assert m["delta1"] == pytest.approx(2 / 3)
    assert m["completeness"] == pytest.approx(3 / 4)
    m2 = depth_metrics(pred, gt, scale=2.0)
    assert m2["absrel"] == pytest.approx((1.2 + 1.0 + 0.0) / 3) and m2["delta1"] == pytest.approx(1 / 3)


def _acos_rotation_deg(R: np.ndarray) -> float:
    """The formula the package used before: acos of the clipped trace cosine."""
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _acos_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


@pytest.mark.parametrize("theta", [1e-7, 1e-8, 1e-10, 1e-13])
def test_pose_angles_are_accurate_for_tiny_angles(theta: float) -> None:
    deg = math.degrees(theta)
    axis = np.array([0.3, -0.8, 0.5])
    R = S.rotation_about(axis, deg)
    assert rotation_angle_deg(R) == pytest.approx(deg, rel=1e-6)
    R_gt = S.rotation_about((1.0, 2.0, -0.5), 37.0)
    if theta >= 1e-10:  # R_gt·R rounds at ~1e-16 absolute: relative 1e-3 down to ~1e-12 rad
        assert rotation_error_deg(R_gt @ R, R_gt) == pytest.approx(deg, rel=1e-3)
    a = np.array([0.2, -0.4, 1.3])
    b = S.rotation_about(np.cross(a, (1.0, 0.0, 0.0)), deg) @ a
    assert angle_between_deg(a, b) == pytest.approx(deg, rel=1e-6)
    assert translation_direction_error_deg(3.0 * a, b) == pytest.approx(deg, rel=1e-6)
    # acos of the rounded cosine: percents off at 1e-7 rad, exactly 0 below ~1e-8 rad
    assert abs(_acos_rotation_deg(R) - deg) > 1e-3 * deg
    assert abs(_acos_angle_deg(a, b) - deg) > 1e-3 * deg


def test_pose_angles_agree_with_acos_at_moderate_angles_and_180() -> None:
    rng = np.random.default_rng(0)
    for deg in [*rng.uniform(0.5, 179.5, 50), 90.0, 180.0]:
        R = S.rotation_about(rng.normal(size=3), deg)
        assert rotation_angle_deg(R) == pytest.approx(deg, abs=1e-9)
        assert rotation_angle_deg(R) == pytest.approx(_acos_rotation_deg(R), abs=1e-6)
        R_gt = S.rotation_about(rng.normal(size=3), float(rng.uniform(0, 180)))
        assert rotation_error_deg(R_gt @ R, R_gt) == pytest.approx(deg, abs=1e-9)
        a = rng.normal(size=3)
        b = S.rotation_about(np.cross(a, rng.normal(size=3)), deg) @ a * 2.5
        assert angle_between_deg(a, b) == pytest.approx(deg, abs=1e-9)
        assert angle_between_deg(a, b) == pytest.approx(_acos_angle_deg(a, b), abs=1e-6)
    t = np.array([0.3, 0.1, -1.0])
    assert translation_direction_error_deg(t, -2 * t) == 180.0
    assert translation_direction_error_deg(t, t) == 0.0
    assert math.isnan(translation_direction_error_deg(t, np.zeros(3)))
    # batched vectors: [M, 3] → [M], the same numbers as one pair at a time, NaN for a zero vector
    A, B = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    B[4] = 0.0
    got = angle_between_deg(A, B)
    assert got.shape == (6,) and math.isnan(got[4])
    want = [angle_between_deg(x, y) for x, y in zip(A, B)]
    np.testing.assert_allclose(np.delete(got, 4), np.delete(want, 4), rtol=0, atol=1e-12)
    # the synthetic generator's pose errors are these
    R0, R1 = S.rotation_about((1, 1, 0), 10.0), S.rotation_about((0, 1, 1), 25.0)
    want_pose = (rotation_error_deg(R0, R1), translation_direction_error_deg(A[0], A[1]))
    assert S.pose_errors(R0, A[0], R1, A[1]) == want_pose


# ------------------------------------------------------------------------------------ baselines
def test_point_discs_nearest_wins() -> None:
    cam = Camera("c", 16, 16, np.array([[10.0, 0.0, 8.0], [0.0, 10.0, 8.0], [0.0, 0.0, 1.0]]), np.eye(4))
    far = PointCloud(np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]], np.float32), np.array([0.1]))
    rgb, covered = render_points(far, cam)
    assert covered.sum() == 4 and covered[7:9, 7:9].all()  # radius 1 px around (8, 8): four pixel centres
    assert (rgb[7:9, 7:9] == [1, 0, 0]).all() and (rgb[~covered] == 0).all()
    both = PointCloud(
        np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.5]]),
        np.array([[1, 0, 0], [0, 1, 0]], np.float32),
        np.array([0.1, 0.06]),
    )
    rgb, covered = render_points(both, cam, config=PointsConfig())
    assert covered.sum() == 4 and (rgb[7:9, 7:9] == [0, 1, 0]).all()  # the nearer point wins
    unseen = PointCloud(np.array([[0.0, 0.0, -1.0], [50.0, 0.0, 1.0]]), np.ones((2, 3), np.float32), np.full(2, 0.1))
    rgb, covered = render_points(unseen, cam, background=(0.5, 0.5, 0.5))  # behind and off screen
    assert not covered.any() and (rgb == 0.5).all()


def test_nearest_context() -> None:
    a, b = translated_camera("a", 0.0), translated_camera("b", 1.0)
    assert nearest_context(translated_camera("t", 0.3), (a, b)) == 0
    assert nearest_context(translated_camera("t", 0.7), (a, b)) == 1


# ------------------------------------------------------------------------------------ protocol
def test_target_camera_in_the_reconstruction_frame() -> None:
    """A world point seen by the true target is seen at the same pixel in camera-0 units scaled by s."""
    rng = np.random.default_rng(1)
    poses = []
    for _ in range(2):
        T = np.eye(4)
        T[:3, :3] = S.rotation_about(rng.normal(size=3), 20.0)
        T[:3, 3] = rng.normal(size=3)
        poses.append(T)
    c0, tgt = Camera("c0", W, H, K, poses[0]), Camera("t", W, H, K, poses[1])
    X = tgt.center + tgt.cam_to_world[:3, 2] * 2.5 + 0.1  # in front of the target
    s = 0.37
    cam = target_camera(tgt, c0, scale=s, width=2 * W, height=2 * H, focal_ratio=(1.0, 1.0))
    X0 = (c0.world_to_cam @ np.append(X, 1.0))[:3] / s  # the point in reconstruction units

    def project(cam: Camera, P: np.ndarray) -> np.ndarray:
        p = cam.K @ (cam.R @ P + cam.t)
        return p[:2] / p[2]

    assert np.allclose(project(cam, X0), 2 * project(tgt, X), atol=1e-9)


@pytest.mark.parametrize("scale", ["metric", "relative"])
def test_ground_truth_reconstruction_scores_40_db_and_no_pose_error(plane: Path, scale: str) -> None:
    ds = load_dataset(plane)
    case = EvalCase("plane", "test", (0, 3), (1, 2, 0))  # two targets between the contexts, and context 0 itself
    oracle = OracleReconstructor(scale=scale, gaussians=GaussianInitConfig(footprint=0.4))  # type: ignore[arg-type]
    r = evaluate_case(ds.scenes[0], case, oracle, EvalConfig(settings=ReconstructSettings(size=512)))
    assert r.status == "ok"
    assert r.rotation_error_deg < 1e-6 and r.translation_error_deg < 1e-6 and r.pose_error_deg < 1e-6
    assert r.scale == pytest.approx(PLANE_X[3] if scale == "relative" else 1.0)
    assert r.depth["absrel"] < 1e-5 and r.depth["delta1"] == 1.0
    assert r.focal_error_pct == [None, None]
    for t in r.targets:
        m = t.metrics["oracle"]
        assert m["psnr"] >= 40.0 and m["psnr_masked"] >= 40.0, (t.name, m)
        assert m["mask_fraction"] == 1.0  # targets between the contexts see nothing new on a plane
        assert t.metrics["points"]["psnr"] > 30.0
    assert r.targets[0].metrics["copy"]["psnr"] < r.targets[0].metrics["oracle"]["psnr"] - 5  # a 1.7 px shift


class _FailingOn:
    """A reconstructor that fails on chosen context pairs and is the oracle elsewhere."""

    name = "oracle"

    def __init__(self, fail: set[tuple[int, int]]) -> None:
        self.fail = fail

    def __call__(self, scene, case, settings):  # noqa: ANN001, ANN204
        if case.context in self.fail:
            raise ReconstructionError("pose could not be estimated: 3 matches")
        return ORACLE(scene, case, settings)


def test_failed_reconstruction_is_counted_not_skipped(plane: Path, tmp_path: Path) -> None:
    ds = load_dataset(plane)
    cases = [EvalCase("plane", "wide", (0, 3), (1,)), EvalCase("plane", "wide", (1, 3), (2,))]
    writer = ResultWriter(tmp_path / "out")
    run = evaluate(ds, cases, _FailingOn({(1, 3)}), EvalConfig(), writer=writer)
    ok, failed = run.results
    assert (ok.status, failed.status) == ("ok", "failed")
    assert failed.error == "pose could not be estimated: 3 matches" and failed.pose_error_deg == 180.0
    assert "copy" in failed.targets[0].metrics and "oracle" not in failed.targets[0].metrics
    row = next(r for r in summarize(run) if r["method"] == "oracle")
    assert (row["cases"], row["failed"], row["targets"]) == (2, 1, 1)
    assert row["auc@5"] == pytest.approx(0.5)  # one perfect pair, one at 180°
    copy = next(r for r in summarize(run) if r["method"] == "copy")
    assert copy["targets"] == 2
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    assert doc["complete"] and [c["status"] for c in doc["cases"]] == ["ok", "failed"]
    assert doc["cases"][1]["pose_error_deg"] == 180.0
    csv_rows = (tmp_path / "out" / "results.csv").read_text().splitlines()
    assert any(",oracle,failed," in line and "3 matches" in line for line in csv_rows)


def test_bad_input_mid_run_keeps_the_finished_cases(plane: Path, tmp_path: Path) -> None:
    root = write_plane_dataset(tmp_path / "p", PLANE_X[:4])
    ds = load_dataset(root)
    png = root / "images" / "f2.png"
    png.write_bytes(png.read_bytes()[:120])  # the header stays readable, the pixels are gone
    cases = [EvalCase("p", "x", (0, 3), (1,)), EvalCase("p", "x", (0, 3), (2,)), EvalCase("p", "x", (1, 3), (0,))]
    writer = ResultWriter(tmp_path / "out")
    run = evaluate(ds, cases, ORACLE, EvalConfig(baselines=()), writer=writer)
    assert [r.status for r in run.results] == ["ok", "error", "ok"]
    assert "f2.png" in run.results[1].error
    assert [r["split"] for r in summarize(run)] == ["x"] and summarize(run)[0]["errors"] == 1
    lines = (tmp_path / "out" / "cases.jsonl").read_text().splitlines()
    assert [json.loads(line)["status"] for line in lines] == ["ok", "error", "ok"]
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    assert doc["errors"][0]["case"] == "p/x/0-3" and "f2.png" in doc["errors"][0]["error"]


# ------------------------------------------------------------------------------------ bench
def test_pareto_front_and_grid() -> None:
    pts = [(1.0, 20.0), (2.0, 25.0), (3.0, 24.0), (0.5, 10.0), (2.0, 25.0), (4.0, math.nan)]
    assert pareto_front(pts, higher_is_better=True) == [0, 1, 3, 4]
    assert pareto_front([(1.0, 5.0), (2.0, 1.0), (3.0, 3.0)], higher_is_better=False) == [0, 1]
    g = grid(["classical"], [256, 512], [None, 0.02], [0, 50])
    assert len(g) == 8 and g[0] == BenchSetting("classical", 256, None, 0)
    rows = [BenchRow(BenchSetting(size=256), {"time_s": 1.0, "psnr": 20.0, "failed": 0, "cases": 2}, pareto=True)]
    md = bench_markdown(rows, "psnr")
    assert (
        "| **classical** | **256** |" in md
        and "classical size=256 tau=default refine=0 quality=balanced: 1.00 s, psnr 20.000" in md
    )


def test_run_bench_writes_table_plot_and_runs(plane: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(BACKENDS, "oracle", lambda config, models=None: ORACLE)
    ds = load_dataset(plane)
    cases = [EvalCase("plane", "x", (0, 3), (1,))]
    rows = run_bench(ds, cases, grid(["oracle"], [64, 96]), metric="psnr", out_dir=tmp_path)
    assert [r.setting.size for r in rows] == [64, 96] and any(r.pareto for r in rows)
    assert all(r.summary["cases"] == 1 for r in rows)
    img = cv2.imread(str(tmp_path / "bench.png"))
    assert img is not None and img.shape == (560, 900, 3)
    assert (tmp_path / "bench.md").read_text().count("| oracle |") + (tmp_path / "bench.md").read_text().count(
        "| **oracle** |"
    ) == 2
    for slug in (
        "oracle_s64_td_r0_qbalanced",
        "oracle_s96_td_r0_qbalanced",
    ):  # both compared at the largest working size
        doc = json.loads((tmp_path / "runs" / slug / "results.json").read_text())
        assert doc["cases"][0]["targets"][0]["size"] == [96, 64]


def test_bench_compares_settings_on_the_cases_all_of_them_reconstructed(
    plane: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(BACKENDS, "oracle", lambda config, models=None: ORACLE)
    monkeypatch.setitem(BACKENDS, "flaky", lambda config, models=None: _FailingOn({(1, 3)}))
    ds = load_dataset(plane)
    cases = [EvalCase("plane", "x", (0, 3), (1,)), EvalCase("plane", "x", (1, 3), (2,))]
    oracle, flaky = run_bench(ds, cases, grid(["oracle", "flaky"], [96]), metric="psnr")
    assert (oracle.summary["failed"], flaky.summary["failed"]) == (0, 1)
    assert oracle.summary["common_targets"] == flaky.summary["common_targets"] == 1
    assert oracle.summary["psnr"] == pytest.approx(flaky.summary["psnr"])  # same reconstruction of the common case
    assert flaky.summary["auc@5"] == pytest.approx(0.5) and oracle.summary["auc@5"] == 1.0
    # equal time and quality: the setting with fewer failures dominates
    assert pareto_front([(1.0, 20.0), (1.0, 20.0), (0.5, 19.0)], True, failures=[0, 1, 2]) == [0, 2]
