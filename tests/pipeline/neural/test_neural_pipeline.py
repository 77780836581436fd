"""``macsplat reconstruct --backend neural``: the neural stages, end to end and one by one.

* The CLI end to end with tiny random-weight checkpoints written in the official layouts (MASt3R
  ``.pth``, DINOv3 ``.pth``, macsplat fusion ``.pth``, Splatt3R Lightning ``.ckpt``): random weights
  give meaningless geometry, which the pose acceptance refuses (``tests/pipeline/pose/test_hostile_pose.py``), so
  these run with ``--accept-low-confidence`` and check the plumbing (exit codes, files, report), not accuracy.
* The pipeline with a stand-in backbone that returns the exact point maps of a ray-traced pair:
  the pose (metric), the focal length and the depth must come out right.
* The geometry routines on synthetic point maps with noise and outliers, descriptor sampling, and
  the shared matcher on dense maps.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from macsplat_cli.cameras import load_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.engine import EngineConfig, Models, build_pipeline, reconstruct
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.images import save_image
from macsplat_cli.neural import MASt3RBackbone
from macsplat_cli.neural.loading import load_pair_predictor
from macsplat_cli.neural.predictor import PairPredictor
from macsplat_cli.pipeline.matching import MatchConfig, match_features
from macsplat_cli.pipeline.neural import NeuralPair, ViewWarp, estimate_focal_weiszfeld, sample_descriptors
from macsplat_cli.pipeline.pose import pose_from_pointmap
from macsplat_cli.pipeline.run import FilteredMatcher
from macsplat_cli.pipeline.types import Features
from macsplat_cli.ply import read_ply

from support.checkpoints import TINY, random_state_dict
from support.cli import run_cli
from support.neural import PAIR, SIZE, OracleBackbone, Scene, backproject
from support.scenes import PairFactory


# ------------------------------------------------------------------------------ helpers and fixtures
@pytest.fixture(scope="module")
def scene(pair_files: PairFactory) -> Scene:
    return Scene(pair_files(PAIR))


@pytest.fixture(scope="module")
def ckpts(tiny_checkpoints: dict[str, Path]) -> dict[str, Path]:
    return tiny_checkpoints


def _neural_args(scene: Scene, out: Path, *extra: str | Path) -> list[str | Path]:
    return ["reconstruct", scene.a, scene.b, "-o", out / "scene.ply", "--backend", "neural", *extra]


ACCEPT = "--accept-low-confidence"  # random weights: a pose the acceptance refuses, written anyway for the plumbing


def _accepting(config: EngineConfig) -> EngineConfig:
    """``config`` with ``accept_low_confidence`` (random weights give a pose the acceptance refuses)."""
    config.pipeline.search.accept_low_confidence = True
    return config


# ------------------------------------------------------------------------------ CLI end to end
def test_cli_neural_end_to_end(scene: Scene, ckpts: dict[str, Path], tmp_path: Path) -> None:
    """Exit 0, a standard PLY, a metric cameras file, renders, and a report naming every backend."""
    code, out, err = run_cli(
        _neural_args(scene, tmp_path, "--weights", ckpts["mast3r"], "--report", tmp_path / "report.json",
                     "--renders", tmp_path / "views", "--num-renders", "2", ACCEPT)
    )  # fmt: skip
    assert code == 0, err
    assert out == "" and "error:" not in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json", "scene.cameras.json", "scene.ply", "views"]
    g = read_ply(tmp_path / "scene.ply")
    assert len(g) > 0 and all(torch.isfinite(t).all() for t in (g.means, g.log_scales, g.quats, g.sh))
    cams = load_cameras(tmp_path / "scene.cameras.json")
    assert cams.scale == "metric" and cams.world == "camera_0" and len(cams) == 2
    assert cams.pose_confidence is not None and cams.pose_confidence["accepted_low_confidence"] is True
    np.testing.assert_array_equal(cams[0].cam_to_world, np.eye(4))
    assert len(list((tmp_path / "views").iterdir())) == 2
    r = json.loads((tmp_path / "report.json").read_text())
    assert r["scale"] == "metric"
    b = r["backends"]
    assert b["descriptors"] == "neural:mast3r-desc24 (semantic fusion skipped)"
    assert b["matching"] == "reciprocal-nn+confidence"  # the shared matcher
    assert b["pose"] == "neural:mast3r-pointmap-pnp" and b["depth"] == "neural:mast3r-pointmap"
    assert b["gaussians"] == "classical:per-pixel-surfels"
    assert b["descriptors_fallback"] is None
    assert b["fusion"].startswith("skipped")
    n = r["neural"]
    assert n["fusion"]["applied"] is False and "skipped" in n["fusion"]["detail"]
    assert b["pair"] == "neural:pair-predictor" and r["times_s"]["network"] > 0  # one pass, the "pair" stage
    assert n["network_size"] == list(SIZE) and n["files"]["weights"] == str(ckpts["mast3r"])
    assert r["keypoints"] == [(SIZE[0] // 4) * (SIZE[1] // 4)] * 2  # the 4-px descriptor grid
    assert r["gaussians_written"] == len(g) == r["gaussians"]


def test_cli_neural_fusion_gaussian_head_and_refine(scene: Scene, ckpts: dict[str, Path], tmp_path: Path) -> None:
    """--dino + --fusion apply the fusion; --gaussian-head gives the head's Gaussians; --refine runs on top."""
    code, out, err = run_cli(
        _neural_args(scene, tmp_path, "--weights", ckpts["mast3r"], "--dino", ckpts["dino"], "--fusion",
                     ckpts["fusion"], "--gaussian-head", ckpts["splatt3r"], "--refine", "3", "--json", "-q", ACCEPT)
    )  # fmt: skip
    assert code == 0, err
    assert "error:" not in err  # -q: only warnings (random weights give an inconsistent pose)
    r = json.loads(out)
    assert r["neural"]["fusion"]["applied"] is True and "applied" in r["neural"]["fusion"]["detail"]
    fusion = "dinov3-custom-64d-2x2h-mlp128+residual-semantic-fusion"  # the tiny variant, inferred from its shapes
    assert r["backends"]["fusion"] == fusion and r["backends"]["descriptors"] == "neural:mast3r-desc24+" + fusion
    assert r["backends"]["gaussians"] == "neural:splatt3r-gaussian-head"
    assert r["neural"]["gaussian_head"] is True
    assert r["refine"]["steps"] >= 1 and r["refine"]["scale"] == 2
    assert load_cameras(tmp_path / "scene.cameras.json").scale == "metric"
    assert len(read_ply(tmp_path / "scene.ply")) == r["gaussians_written"] > 0


def _one_error_line(err: str, *, after_progress: bool = False) -> str:
    """The single ``error:`` line; with ``after_progress``, it may follow the failed stage's progress line."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if after_progress:
        assert all(ln.lstrip().startswith("✗") and ln.rstrip().endswith("failed") for ln in lines[:-1]), err
        lines = lines[-1:]
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ")
    return lines[0]


def test_cli_neural_without_weights_names_the_file(scene: Scene, tmp_path: Path) -> None:
    code, out, err = run_cli(_neural_args(scene, tmp_path))
    assert code == 2 and out == ""
    line = _one_error_line(err)
    assert "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth" in line
    assert "huggingface.co/naver" in line and "--weights" in line and "models/mast3r.md" in line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("which", "key"),
    [("bad", "dec_blocks.1.mlp.fc1.weight"), ("splatt3r-alone", "encoder.patch_embed.proj.weight")],
)
def test_cli_neural_mismatched_checkpoint_names_the_key(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path, which: str, key: str
) -> None:
    """A file that does not fit: exit 2, the first bad key named, no output written.

    A tiny Splatt3R file alone is read as the released architecture (its OmegaConf config is not read).
    """
    opts = ["--weights", ckpts["bad"]] if which == "bad" else ["--gaussian-head", ckpts["splatt3r"]]
    code, _, err = run_cli(_neural_args(scene, tmp_path, *opts))
    assert code == 2
    assert f"'{key}'" in _one_error_line(err, after_progress=True)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("opts", "message"),
    [
        (["--dino", "DINO"], "--dino needs --fusion"),
        (["--fusion", "FUSION"], "--fusion needs --dino"),
        (["--device", "tpu"], "--device 'tpu'"),
        (["--weights", "nope.pth"], "MASt3R checkpoint not found: nope.pth"),
    ],
)
def test_cli_neural_bad_options(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path, opts: list[str], message: str
) -> None:
    opts = [{"DINO": str(ckpts["dino"]), "FUSION": str(ckpts["fusion"])}.get(o, o) for o in opts]
    if "--weights" not in opts:
        opts += ["--weights", str(ckpts["mast3r"])]
    code, _, err = run_cli(_neural_args(scene, tmp_path, *opts))
    assert code == 2
    assert message in _one_error_line(err, after_progress="nope.pth" in opts)  # files are read under a progress line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cli_neural_cuda_unavailable(scene: Scene, ckpts: dict[str, Path], tmp_path: Path) -> None:
    code, _, err = run_cli(_neural_args(scene, tmp_path, "--weights", ckpts["mast3r"], "--device", "cuda"))
    assert code == 2
    assert "CUDA is not available" in _one_error_line(err)


def test_cli_classical_rejects_neural_options(scene: Scene, ckpts: dict[str, Path], tmp_path: Path) -> None:
    args = ["reconstruct", scene.a, scene.b, "-o", tmp_path / "s.ply", "--weights", ckpts["mast3r"]]
    code, _, err = run_cli(args)
    assert code == 2
    assert "--weights only apply to --backend neural" in _one_error_line(err)


# ------------------------------------------------------------------------------ pipeline with exact point maps
def test_pipeline_recovers_metric_pose_focal_and_depth(scene: Scene) -> None:
    """Exact point maps in → the true relative pose in metres, the true focal length, the true depth."""
    oracle = OracleBackbone(scene)
    models = Models(predictor=PairPredictor(oracle))  # type: ignore[arg-type]
    rec = reconstruct([scene.a, scene.b], EngineConfig(backend="neural"), models=models)
    assert oracle.calls == 1  # one forward pass for descriptors, pose, depth and Gaussians
    assert rec.scale == "metric" and rec.cameras().scale == "metric" and rec.report.scale == "metric"
    geo = rec.pose.geometry
    rot_err, t_err = syn.pose_errors(geo.R, geo.t, scene.R, scene.t)
    assert rot_err < 0.05 and t_err < 0.1, (rot_err, t_err)
    assert np.linalg.norm(geo.t) == pytest.approx(np.linalg.norm(scene.t), rel=1e-3)  # metric: no unit baseline
    for K, cam in ((geo.K0, scene.cam0), (geo.K1, scene.cam1)):  # 50° field of view, not the 60° prior
        assert K[0, 0] == pytest.approx(cam.K[0, 0], rel=1e-3)
    assert [im.intrinsics_source for im in rec.report.images] == ["estimated", "estimated"]
    for d, gt in zip(rec.depths, (scene.depth0, scene.depth1)):
        sel = d.valid & (gt > 0)
        assert sel.mean() > 0.95
        np.testing.assert_allclose(d.depth[sel], gt[sel], rtol=1e-3)
    # matching on the dense descriptor maps, verified against the point maps: correct to a few pixels
    m = geo.inliers
    assert rec.report.matches["verified"] == len(m) > 60
    X = backproject(scene.depth0, scene.cam0.K)[(m.xy0[:, 1]).astype(int), (m.xy0[:, 0]).astype(int)]
    uv = (X @ scene.R.T + scene.t) @ scene.cam1.K.T
    err = np.linalg.norm(uv[:, :2] / uv[:, 2:] - m.xy1, axis=1)
    assert np.median(err) < 1.0 and np.mean(err < 2.0) > 0.9  # snapped off the 4-px grid by refine_matches
    # the report is JSON and names the stages
    r = json.loads(json.dumps(rec.report.to_json()))
    assert r["pose"]["method"] == "pnp-ransac" and r["pose"]["pnp_inlier_ratio"] > 0.95
    # accepted by the same acceptance as a classical pose: checked, no doubt (measured: confidence 0.86)
    assert r["pose"]["doubts"] == [] and r["pose"]["confidence"] > 0.5 and "refit_rotation_deg" in r["pose"][
        "confidence_checks"
    ]  # fmt: skip
    assert r["inlier_ratio"] == pytest.approx(len(m) / r["matches"]["confident"])  # verified / candidates


def test_pipeline_with_given_intrinsics_keeps_them(scene: Scene, tmp_path: Path) -> None:
    from macsplat_cli.cameras import CameraSet, save_cameras
    from macsplat_cli.pipeline.views import ViewConfig

    save_cameras(tmp_path / "cams.json", CameraSet([scene.cam0.rescaled(*SIZE)], scale="metric"))
    config = EngineConfig(backend="neural")
    config.pipeline.views = ViewConfig(intrinsics=tmp_path / "cams.json")
    rec = reconstruct([scene.a, scene.b], config, models=Models(predictor=PairPredictor(OracleBackbone(scene))))
    np.testing.assert_allclose(rec.pose.geometry.K0, scene.cam0.K)
    assert rec.pose.geometry.focal_estimated is False
    assert syn.pose_errors(rec.pose.geometry.R, rec.pose.geometry.t, scene.R, scene.t)[0] < 0.05


# ------------------------------------------------------------------------------ geometry units
def _synthetic_pointmap(f: float, w: int = 160, h: int = 120, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A wavy surface seen by a pinhole camera with focal ``f``: (points [H, W, 3], K)."""
    rng = np.random.default_rng(seed)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    ys, xs = np.mgrid[0:h, 0:w]
    depth = 2.0 + 0.5 * np.sin(xs / 17.0) * np.cos(ys / 11.0) + 0.3 * rng.random((h, w))
    return backproject(depth, K), K


@pytest.mark.parametrize("fov", [40.0, 60.0, 85.0])
def test_weiszfeld_focal_recovers_the_focal(fov: float) -> None:
    w, h = 160, 120
    f = w / (2 * math.tan(math.radians(fov) / 2))
    pts, _ = _synthetic_pointmap(f)
    assert estimate_focal_weiszfeld(pts) == pytest.approx(f, rel=1e-9)
    # depth noise along the rays leaves it exact; 20 % wild outliers move the robust fit by < 1 %
    rng = np.random.default_rng(1)
    noisy = pts * (1 + 0.05 * rng.standard_normal((h, w)))[..., None]
    bad = rng.random((h, w)) < 0.2
    noisy[bad] = rng.uniform(-2, 2, (int(bad.sum()), 3)) + [0, 0, 3]
    assert estimate_focal_weiszfeld(noisy) == pytest.approx(f, rel=0.01)
    # masked-out pixels are ignored; NaNs and points behind the camera too
    noisy[bad] = np.nan
    assert estimate_focal_weiszfeld(noisy, mask=~bad) == pytest.approx(f, rel=1e-6)


def test_weiszfeld_focal_is_clipped_around_the_prior() -> None:
    pts, _ = _synthetic_pointmap(30.0)  # a 138° field of view
    base = 160 / (2 * math.tan(math.radians(30.0)))
    assert estimate_focal_weiszfeld(pts) == pytest.approx(0.5 * base)
    assert estimate_focal_weiszfeld(pts, focal_range=(0.1, 3.5)) == pytest.approx(30.0, rel=1e-6)
    with pytest.raises(ReconstructionError):
        estimate_focal_weiszfeld(-pts)  # everything behind the camera


def _rotation(axis: list[float], deg: float) -> np.ndarray:
    import cv2

    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * math.radians(deg))[0]


def test_pose_from_pointmap_recovers_a_known_pose_with_noise_and_outliers() -> None:
    """View 1's point map in camera 0's frame + its pixels → X_cam1 = R·X_cam0 + t, metric."""
    rng = np.random.default_rng(0)
    pts1, K = _synthetic_pointmap(150.0)  # view 1's points in its own frame
    R, t = _rotation([0.2, 1.0, 0.1], 25.0), np.array([-0.8, 0.05, 0.2])
    h, w = pts1.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    xy = np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)
    P1 = pts1.reshape(-1, 3)
    P1 = P1 * (1 + 0.03 * rng.standard_normal(len(P1)))[:, None]  # depth noise along view 1's rays
    P1 = P1 + 0.002 * rng.standard_normal(P1.shape) * P1[:, 2:]  # and a little everywhere (≈0.3 px)
    X = (P1 - t) @ R  # in camera 0's frame
    bad = rng.random(len(X)) < 0.15
    X[bad] = rng.uniform(-3, 3, (int(bad.sum()), 3)) + [0, 0, 3]
    res = pose_from_pointmap(xy, X, K)
    rot_err, t_err = syn.pose_errors(res.R, res.t, R, t)
    assert rot_err < 0.2 and t_err < 0.5, (rot_err, t_err)
    assert np.linalg.norm(res.t) == pytest.approx(np.linalg.norm(t), rel=0.01)
    assert res.inliers[~bad].mean() > 0.95 and res.inliers[bad].mean() < 0.1
    with pytest.raises(ReconstructionError, match="only 3 pixels"):
        pose_from_pointmap(xy[:3], X[:3], K)


def test_view_warp_keeps_intrinsics_consistent() -> None:
    """A view of another size: scaled to cover the network size, centre-cropped; K follows the pixels."""
    warp = ViewWarp.fit((120, 80), (96, 64))  # 1.5 : 1 → 1.5 : 1 exactly: scale 0.8, no crop
    assert warp.scale == (0.8, 0.8) and warp.offset == (0, 0)
    warp = ViewWarp.fit((64, 64), (96, 64))  # square → landscape: scale 1.5, crop 16 px top and bottom
    assert warp.scale == (1.5, 1.5) and warp.offset == (0, 16)
    K = np.array([[70.0, 0, 32], [0, 70.0, 32], [0, 0, 1]])
    X = np.array([[0.1, -0.2, 2.0], [-0.3, 0.25, 1.5]])
    p = X @ K.T
    xy = p[:, :2] / p[:, 2:]
    pn = X @ warp.K_net(K).T
    np.testing.assert_allclose(warp.to_net(xy), pn[:, :2] / pn[:, 2:], atol=1e-12)
    np.testing.assert_allclose(warp.from_net(warp.to_net(xy)), xy, atol=1e-12)
    img = np.zeros((64, 64, 3), np.float32)
    img[40:44, 10:14] = 1.0  # a bright square at view pixels x 10–14, y 40–44
    net = warp.image(img)
    assert net.shape == (64, 96, 3)
    ys, xs = np.nonzero(net[..., 0] > 0.5)
    np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5], warp.to_net(np.array([[12.0, 42.0]]))[0], atol=0.6)
    back, inside = warp.sample(np.arange(64 * 96, dtype=float).reshape(64, 96))
    assert back.shape == (64, 64) and inside[11:53].all() and not inside[:10].any() and not inside[54:].any()


# ------------------------------------------------------------------------------ descriptors and matching
def test_sample_descriptors_grid_topk_and_mask() -> None:
    h, w = 12, 16
    conf = np.arange(h * w, dtype=np.float32).reshape(h, w)
    idx, grid = sample_descriptors(conf, stride=4)
    assert grid == (3, 4)
    np.testing.assert_array_equal(idx, [(r * w + c) for r in (2, 6, 10) for c in (2, 6, 10, 14)])
    idx, grid = sample_descriptors(conf, sampling="topk", top_k=5)
    assert grid is None and sorted(idx.tolist()) == list(range(h * w - 5, h * w))
    mask = np.ones((h, w), bool)
    mask[:, :8] = False
    idx, grid = sample_descriptors(conf, stride=4, mask=mask)
    assert grid is None and len(idx) == 6 and (idx % w >= 8).all()


def test_shared_matcher_on_dense_descriptor_maps() -> None:
    """Two dense maps, the second shifted by 8 px: grid-sampled descriptors match at the true shift,
    and the joint-confidence gate drops the region where view 1 is unsure."""
    rng = np.random.default_rng(0)
    h, w, shift = 48, 64, 8
    scene = F.normalize(torch.from_numpy(rng.standard_normal((h, w + shift, 24))).float(), dim=-1).numpy()
    desc0, desc1 = scene[:, :w], scene[:, shift:]  # view-1 pixel x shows view-0 pixel x + 8
    conf0 = np.full((h, w), 2.0, np.float32)
    conf1 = np.full((h, w), 2.0, np.float32)
    conf1[: h // 2] = 0.1  # unsure in the top half: joint confidence 0.2 < τ = 1

    def features(desc: np.ndarray, conf: np.ndarray) -> Features:
        idx, grid = sample_descriptors(conf, stride=4)
        xy = np.stack([idx % w + 0.5, idx // w + 0.5], 1)
        return Features(xy, desc.reshape(-1, 24)[idx], conf.reshape(-1)[idx], grid=grid)

    matcher = FilteredMatcher(MatchConfig(conf_threshold=1.0, ratio_confidence=False))
    f0, f1 = features(desc0, conf0), features(desc1, conf1)
    every = match_features(f0, f1, MatchConfig(conf_threshold=0.0, ratio_confidence=False))
    right = (every.xy0[:, 0] - every.xy1[:, 0] == shift) & (every.xy0[:, 1] == every.xy1[:, 1])
    assert right.sum() == (h // 4) * ((w - shift) // 4)  # every grid point that both views see
    assert (~right).sum() <= 3  # chance pairs among the columns that only one view sees
    m = matcher(f0, f1)
    assert m.counts == {"reciprocal": len(every), "confident": len(m)}
    assert (m.xy1[:, 1] > h // 2).all() and np.all(m.conf > 1.0)  # the unsure half is gated out
    assert np.sum((m.xy0[:, 0] - m.xy1[:, 0] == shift) & (m.xy0[:, 1] == m.xy1[:, 1])) == right.sum() // 2


def _tiny_predictor() -> PairPredictor:
    torch.manual_seed(0)
    net = MASt3RBackbone(TINY).eval()
    net.load_state_dict(random_state_dict(TINY))
    return PairPredictor(net).eval()


def test_pair_stage_runs_the_network_once_and_the_stages_read_it(scene: Scene) -> None:
    """The ``pair`` stage runs the predictor once; the descriptor stage only reads its output."""
    from macsplat_cli.pipeline.neural import NeuralDescriptors
    from macsplat_cli.pipeline.views import load_views

    predictor = _tiny_predictor()
    calls = []
    predictor.register_forward_hook(lambda *args: calls.append(1))
    views = load_views([scene.a, scene.b])
    pair = NeuralPair(predictor)(views)
    assert len(calls) == 1 and pair.net_size == SIZE
    stage = NeuralDescriptors(predictor)
    f0, f1 = stage(views, pair)
    again = stage(views, pair)
    assert len(calls) == 1 and len(f0) == len(f1) == (SIZE[0] // 4) * (SIZE[1] // 4)
    assert f0.desc.shape == (len(f0), 24) and np.allclose(np.linalg.norm(f0.desc, axis=1), 1.0, atol=1e-5)
    assert (f0.conf >= 0).all()
    np.testing.assert_array_equal(again[0].desc, f0.desc)


def test_pair_predictor_is_tensor_in_tensor_out(ckpts: dict[str, Path]) -> None:
    """``PairPredictor.forward``: images in [0, 1] → the backbone's outputs (views stacked on dim 1, the
    descriptor confidence's floor removed) and the head's Gaussians, bit-identical to running the modules
    one by one; ``predict`` names the same tensors."""
    predictor = load_pair_predictor(weights=ckpts["mast3r"], gaussian_head=ckpts["splatt3r"])
    torch.manual_seed(3)
    img0, img1 = torch.rand(2, 3, SIZE[1], SIZE[0]), torch.rand(2, 3, SIZE[1], SIZE[0])
    with torch.no_grad():
        outputs = predictor(img0, img1)
        pred = predictor.predict(img0, img1)
        o0, o1 = predictor.backbone(img0 * 2 - 1, img1 * 2 - 1)
        g0, g1 = predictor.gaussian_head(o0, o1, img0, img1)
    assert all(isinstance(t, torch.Tensor) for t in outputs) and len(outputs) == len(predictor.output_names) == 9
    torch.testing.assert_close(outputs[0], torch.stack([o0.pts3d, o1.pts3d], 1), rtol=0, atol=0)
    torch.testing.assert_close(pred.pts3d, outputs[0], rtol=0, atol=0)
    torch.testing.assert_close(pred.desc[:, 1], o1.desc, rtol=0, atol=0)
    vmin = predictor.backbone.config.desc_conf_mode[1]
    torch.testing.assert_close(pred.desc_conf[:, 0], (o0.desc_conf - vmin).clamp_min(0), rtol=0, atol=0)
    assert pred.gaussians is not None
    for mine, ref in zip(pred.gaussians, (g0, g1)):
        for a, b in zip(mine.tensors(), ref.tensors()):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(Exception, match="img1"):
        predictor(img0, img1[:, :, :32])


def test_fusion_changes_descriptors_and_head_gaussians_keep_their_frame(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path
) -> None:
    """Library path with every file: the fused descriptors differ from MASt3R's own (trained-like fusion);
    the head's Gaussians, moved into camera 1's frame, come back to the head's camera-0 positions in the
    world; a second photo of another size is fitted to the network and mapped back to its own pixels."""
    import cv2

    from macsplat_cli.pipeline.views import load_views

    small = tmp_path / "b_small.png"  # 80×64: another aspect ratio than view 0's 96×64
    save_image(small, cv2.resize(cv2.imread(str(scene.b))[..., ::-1], (80, 64)).astype(np.float32) / 255.0)
    predictor = load_pair_predictor(
        weights=ckpts["mast3r"], gaussian_head=ckpts["splatt3r"], dino=ckpts["dino"], fusion=ckpts["fusion"]
    )
    pipeline = build_pipeline(_accepting(EngineConfig(backend="neural")), Models(predictor=predictor))
    rec = pipeline.run([scene.a, small])
    pred = pipeline.pair.last
    assert pred is not None and predictor.fusion_enabled
    v0, v1 = load_views([scene.a, small])
    img = torch.from_numpy(np.stack([v0.image, pred.warps[1].image(v1.image)])).permute(0, 3, 1, 2) * 2 - 1
    with torch.no_grad():
        raw1, raw2 = predictor.backbone(img[:1], img[1:])
    assert not np.allclose(pred.desc, torch.cat([raw1.desc, raw2.desc]).numpy(), atol=1e-3)
    np.testing.assert_allclose(pred.pts3d[1], raw2.pts3d[0].numpy(), rtol=1e-5, atol=1e-6)  # same forward pass
    # view 1: an 80×64 photo, a 96×64 network input: scaled to 96×77, then rows 6–69 kept
    assert pred.warps[1].scale == (1.2, 77 / 64) and pred.warps[1].offset == (0, 6)
    maps = rec.maps
    assert maps[0].size == (64, 96) and maps[1].size == (64, 80) and rec.depths[1].depth.shape == (64, 80)
    assert pred.gaussians is not None
    head0, head1 = pred.gaussians
    world0 = maps[0].to_gaussians().means
    np.testing.assert_allclose(world0.numpy(), head0.means[0][maps[0].valid[0]].numpy(), atol=1e-5)
    # view 1: back in the world (camera 0) frame, each Gaussian is the head's at the network pixel it came from
    ys, xs = np.nonzero(maps[1].valid[0].numpy())
    uv = pred.warps[1].to_net(np.stack([xs + 0.5, ys + 0.5], 1))
    i, j = np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)
    world1 = maps[1].to_gaussians()
    np.testing.assert_allclose(world1.means.numpy(), head1.means[0][i, j].numpy(), rtol=1e-4, atol=1e-5)
    q_head = head1.quats[0][i, j].double()
    q_world = world1.quats.double() / world1.quats.double().norm(dim=-1, keepdim=True)
    assert torch.allclose((q_world * q_head).sum(-1).abs(), torch.ones(len(q_head), dtype=torch.float64), atol=1e-4)
    np.testing.assert_allclose(world1.sh[:, 0].numpy(), head1.sh[0][i, j, 0].numpy(), atol=1e-6)


def test_eval_with_the_neural_backend(ckpts: dict[str, Path], tmp_path: Path) -> None:
    """``macsplat eval --backend neural`` runs the network on every case (random weights: the poses
    are whatever they are, but every case is measured or counted as failed, none skipped); without
    weights it stops before any case with exit 2."""
    from macsplat_cli.datasets import synthetic as syn

    data = tmp_path / "data"
    room = syn.make_scene("room", 0)
    cams = syn.orbit_cameras(room, [0.0, 6.0, 12.0], width=SIZE[0], height=SIZE[1])
    syn.write_dataset(data, room, [dataclasses.replace(c, name=f"f{i}") for i, c in enumerate(cams)], supersample=1)
    args = ["eval", "--data", data, "--backend", "neural", "--max-pairs", "1", "--max-targets", "1", "--json", "-q",
            "--size", str(SIZE[0])]  # fmt: skip
    code, out, err = run_cli([*args, "--out", tmp_path / "r", "--weights", ckpts["mast3r"]])
    assert code == 0, err
    doc = json.loads((tmp_path / "r" / "results.json").read_text())
    assert doc["cases_done"] == doc["cases_total"] > 0
    assert {c["method"] for c in doc["cases"]} == {"neural"}
    assert all(c["status"] in ("ok", "failed") for c in doc["cases"])
    code, _, err = run_cli([*args, "--out", tmp_path / "s"])
    assert code == 2 and "mast3r" in err.lower() and not (tmp_path / "s").exists()
    code, _, err = run_cli(["eval", "--data", data, "--weights", ckpts["mast3r"], "--out", tmp_path / "c", "-q"])
    assert code == 2 and "--backend neural" in err  # the weights would be ignored by the classical backend

    # and the bench grid over it
    bench = ["bench", "--data", data, "--backend", "neural", "--size", str(SIZE[0]), "--refine", "0,2",
             "--max-pairs", "1", "--max-targets", "1", "-q", "--weights", ckpts["mast3r"],
             "--out", tmp_path / "b"]  # fmt: skip
    code, _, err = run_cli(bench)
    assert code == 0, err
    rows = json.loads((tmp_path / "b" / "bench.json").read_text())
    assert (tmp_path / "b" / "bench.md").is_file() and (tmp_path / "b" / "bench.png").is_file()
    assert "neural" in json.dumps(rows)


def test_bf16_precision_matches_fp32_and_runs_from_the_cli(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path
) -> None:
    """bf16 autocast gives the fp32 point maps to bfloat16 precision; --precision bf16 runs end to end and is
    reported; the option is refused for the classical backend and for unknown values."""
    from macsplat_cli.pipeline.neural import NeuralConfig
    from macsplat_cli.pipeline.views import load_views

    predictor = _tiny_predictor()
    views = load_views([scene.a, scene.b])
    fp32 = NeuralPair(predictor)(views)
    bf16 = NeuralPair(predictor, NeuralConfig(precision="bf16"))(views)
    assert bf16.pts3d.dtype == np.float32 and np.isfinite(bf16.pts3d).all() and np.isfinite(bf16.desc).all()
    rel = np.abs(bf16.pts3d - fp32.pts3d) / np.maximum(np.abs(fp32.pts3d), 1e-3)
    assert np.median(rel) < 0.05  # bfloat16 keeps 8 bits of mantissa
    assert not np.array_equal(bf16.pts3d, fp32.pts3d)  # autocast did run in bfloat16

    code, _, err = run_cli(_neural_args(scene, tmp_path, "--weights", ckpts["mast3r"], "--precision", "bf16", "-q",
                                     "--report", tmp_path / "r.json", ACCEPT))  # fmt: skip
    assert code == 0, err
    assert json.loads((tmp_path / "r.json").read_text())["neural"]["config"]["precision"] == "bf16"
    code, _, err = run_cli(["reconstruct", scene.a, scene.b, "-o", tmp_path / "c.ply", "--precision", "bf16"])
    assert code == 2 and "--precision" in err
    code, _, err = run_cli(_neural_args(scene, tmp_path, "--weights", ckpts["mast3r"], "--precision", "fp8"))
    assert code == 2 and "fp8" in err


def test_network_input_keeps_the_photo_aspect(tmp_path: Path) -> None:
    """MASt3R's loader keeps the photo's aspect and centre-crops to multiples of 16; the working image
    (both sides rounded to multiples of 16) is stretched, so view 0 is warped back to the true aspect."""
    from macsplat_cli.pipeline.views import ViewConfig, load_views

    rng = np.random.default_rng(0)
    photo = cv2_blur(rng.uniform(0, 1, (140, 200, 3)).astype(np.float32))
    for name in ("a.png", "b.png"):
        save_image(tmp_path / name, photo)
    views = load_views([tmp_path / "a.png", tmp_path / "b.png"], ViewConfig(size=96))
    assert (views[0].width, views[0].height) == (96, 64)  # 96 x 67.2 rounded: a 4.8 % stretch
    pair = NeuralPair(_tiny_predictor())(views)
    w0 = pair.warps[0]
    assert w0.net_size == (96, 64) and w0.scale == (1.0, 67 / 64) and w0.offset == (0, 1)
    K_work, K_net = views[0].K, w0.K_net(views[0].K)
    assert abs(K_work[1, 1] / K_work[0, 0] - 1) > 0.04 and abs(K_net[1, 1] / K_net[0, 0] - 1) < 0.005
    # the 224 checkpoints: a centre square crop of side 224
    square = ViewWarp.mast3r((512, 336), (1024, 680), square=224)
    assert square.net_size == (224, 224) and square.offset == ((round(1024 * 224 / 680) - 224) // 2, 0)
    # a square photo is cut to 4:3 (the 512 checkpoints never saw squares)
    assert ViewWarp.mast3r((512, 512), (800, 800)).net_size == (512, 384)


def cv2_blur(img: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), 2.0)


def test_fusion_auto_skips_dinov3_while_matches_verify_and_runs_it_on_demand(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path
) -> None:
    """``--quality fast`` (fusion "auto"): ``forward_unfused`` + ``fuse_descriptors`` is ``forward`` exactly;
    with enough verified matches (and a pose that stands) DINOv3 never runs and the report says why; with too few,
    the fusion runs on demand as the descriptor fallback and its descriptors are the ones "always" gives."""
    predictor = load_pair_predictor(weights=ckpts["mast3r"], dino=ckpts["dino"], fusion=ckpts["fusion"])
    img = torch.rand(2, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        full = predictor(img[:1], img[1:])
        raw = predictor.forward_unfused(img[:1], img[1:])
        fused = predictor.fuse_descriptors(raw[2], img[:1], img[1:])
    for k, (a, b) in enumerate(zip(full, raw)):
        if k != 2:
            assert torch.equal(a, b)
    assert torch.equal(fused, full[2]) and not torch.allclose(raw[2], full[2], atol=1e-3)

    calls = []
    hook = predictor.dino.register_forward_hook(lambda *_: calls.append(1))
    try:
        always = build_pipeline(_accepting(EngineConfig(backend="neural")), Models(predictor=predictor))
        always.run([scene.a, scene.b])
        assert len(calls) == 1
        fast = _accepting(EngineConfig(backend="neural", quality="fast"))
        fast.pipeline.search.fallback_min_inliers = 0  # every pair verifies "enough": the fusion is never needed
        # ... and its pose stands (random weights give a pose that the matches do not single out: a doubted pose
        # tries the fallback tier too)
        fast.pipeline.search.confidence = False
        skip = build_pipeline(fast, Models(predictor=predictor))
        rec_skip = skip.run([scene.a, scene.b])
        assert len(calls) == 1  # DINOv3 did not run
        assert skip.pair.last.fusion == "deferred" and not rec_skip.report.fallback_used
        rep = skip.pair.report().fusion
        assert rep.applied is False and rep.policy == "auto" and "skipped" in rep.detail
        # the unfused pass gives the same geometry (the fusion only changes the descriptors)
        np.testing.assert_array_equal(skip.pair.last.pts3d, always.pair.last.pts3d)
        fast.pipeline.search.fallback_min_inliers = 10**9  # never enough: the fusion runs once, on demand
        demand = build_pipeline(fast, Models(predictor=predictor))
        demand.run([scene.a, scene.b])
        assert len(calls) == 2
        last = demand.pair.last
        assert last.fusion == "applied" and last.fusion_seconds > 0
        np.testing.assert_allclose(last.desc, always.pair.last.desc, atol=1e-6)
        rep = demand.pair.report().fusion
        assert rep.applied is True and "on demand" in rep.detail
        assert demand.backends()["descriptors_fallback"].endswith("(on demand)")
        # through the CLI: the report says what ran
        code, out, err = run_cli(
            [
                *_neural_args(
                    scene, tmp_path, "--weights", ckpts["mast3r"], "--dino", ckpts["dino"], "--fusion", ckpts["fusion"]
                ),
                "--quality",
                "fast",
                "--json",
                "-q",
                ACCEPT,
            ]
        )
        assert code == 0, err
        fusion = json.loads(out)["neural"]["fusion"]
        assert fusion["policy"] == "auto"
        assert ("skipped" in fusion["detail"]) != fusion["applied"]
        assert not fusion["applied"] or "matches_kept" in fusion
    finally:
        hook.remove()


def test_a_neural_stage_without_the_networks_pass_says_so() -> None:
    """The pass is typed (``PairPass``): a neural stage handed None (no ``pair`` slot) says what is missing."""
    from macsplat_cli.pipeline.neural import NeuralDepth

    with pytest.raises(ValueError, match="the network's pass"):
        NeuralDepth()([], None, None)  # type: ignore[arg-type]
