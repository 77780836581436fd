"""Hostile input to the pose stage and its acceptance (issue 23, the second round of hostile input).

* A network whose point maps are nonsense (random weights in the official layout, or a stand-in returning
  shape-correct noise) gave a pose that was written with exit 0 (0–1 verified matches, 0 % PnP agreement, only a
  log warning). The neural pose now goes through the classical acceptance (:func:`accept_pose`): exit 3 naming the
  failing figure, or the scene written and flagged with ``--accept-low-confidence``; exact point maps still pass.
* A pair at ``--size 128`` crashed the pose stage with OpenCV's ``!model.empty()`` assertion (exit 1, "internal
  error"). Not the CMYK JPEG of the report (OpenCV decodes CMYK and YCCK JPEGs to the right colours:
  ``tests/test_images.py``); the cause is repeated correspondences (one keypoint with several SIFT orientations
  matched more than once: 441 matches, 396 distinct), which make USAC's minimal samples degenerate. Every OpenCV
  geometry call of the pose stage now runs within its preconditions; degenerate matches are a
  :class:`ReconstructionError`, never a ``cv2.error``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from macsplat_cli.cameras import load_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.engine import EngineConfig, Models, reconstruct
from macsplat_cli.errors import NonFiniteError, ReconstructionError
from macsplat_cli.neural import BackboneConfig, BackboneView
from macsplat_cli.neural.predictor import PairPredictor
from macsplat_cli.pipeline.pose import PoseConfig, estimate_pose, find_homography, pose_from_pointmap
from macsplat_cli.pipeline.pose import search as search_module
from macsplat_cli.pipeline.pose.robust import robust_fit
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, Reconstruction
from macsplat_cli.pipeline.types import Matches, View
from macsplat_cli.pipeline.views import ViewConfig

from support.cli import run_cli
from support.neural import PAIR, SIZE, OracleBackbone, Scene
from support.scenes import PairFactory, PairSpec, rendered_pair


# ------------------------------------------------------------------------------ fixtures and helpers
@pytest.fixture(scope="module")
def scene(pair_files: PairFactory) -> Scene:
    return Scene(pair_files(PAIR))


@pytest.fixture(scope="module")
def ckpts(tiny_checkpoints: dict[str, Path]) -> dict[str, Path]:
    return tiny_checkpoints


TOO_FEW_VERIFIED = r"only \d+ verified match(es)? agrees? with the pose, need at least 15"


def _error_line(err: str) -> str:
    """The one ``error:`` line (after the progress lines of the stages that ran and the one that failed)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and "internal error" not in err, err
    assert sum("error:" in ln for ln in lines) == 1 and lines[-1].startswith("error: "), err
    return lines[-1]


class NoiseBackbone(torch.nn.Module):
    """A network that returns shape-correct nonsense: point maps of uniform noise in front of the camera, noise
    descriptors, confident everywhere."""

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        self.config = BackboneConfig.tiny()
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[BackboneView, BackboneView]:
        b, _, h, w = img1.shape
        g = self.generator
        views = []
        for _ in range(2):
            pts = torch.rand(b, h, w, 3, generator=g) * torch.tensor([4.0, 4.0, 4.0]) + torch.tensor([-2.0, -2.0, 1.0])
            desc = torch.nn.functional.normalize(torch.randn(b, h, w, 24, generator=g), dim=-1)
            conf, desc_conf = torch.full((b, h, w), 5.0), torch.full((b, h, w), 3.0)
            views.append(BackboneView(pts, conf, desc, desc_conf, (), (h // 16, w // 16)))
        return views[0], views[1]


class UnrelatedDescriptors(OracleBackbone):
    """The exact point maps of the scene, but descriptors of noise: the PnP agrees, the matches do not."""

    def __init__(self, scene: Scene) -> None:
        super().__init__(scene)
        g = torch.Generator().manual_seed(1)
        self.desc = [torch.nn.functional.normalize(torch.randn(d.shape, generator=g), dim=-1) for d in self.desc]


def _neural(scene: Scene, predictor: torch.nn.Module, *, accept: bool = False) -> Reconstruction:
    """The scene's pair through the neural backend with ``predictor`` in place of MASt3R."""
    config = EngineConfig(backend="neural")
    config.pipeline.search.accept_low_confidence = accept
    models = Models(predictor=PairPredictor(predictor))  # type: ignore[arg-type]
    return reconstruct([scene.a, scene.b], config, models=models)


# ---------------------------------------------------------------------- 1. the neural pose, accepted as a classical one
def test_random_weight_network_pose_is_refused_naming_the_figure(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path
) -> None:
    """Tiny random weights in the official MASt3R layout: exit 3, one line naming the PnP agreement, nothing
    written (before: exit 0 and a scene, 0 verified matches, a log warning)."""
    out = tmp_path / "out"
    out.mkdir()
    code, stdout, err = run_cli(["reconstruct", scene.a, scene.b, "-o", out / "scene.ply", "--backend", "neural",
                              "--weights", ckpts["mast3r"]])  # fmt: skip
    assert code == 3, err
    line = _error_line(err)
    assert re.search(r"only \d+ of \d+ confident pixels \(\d+ %\) agree with the PnP pose, need 20 %", line), line
    assert "--accept-low-confidence" in line
    assert stdout == "" and list(out.iterdir()) == []


def test_random_weight_network_pose_is_written_flagged_with_accept_low_confidence(
    scene: Scene, ckpts: dict[str, Path], tmp_path: Path
) -> None:
    """``--accept-low-confidence``: exit 0, and the report, the cameras file and the summary say the pose may be
    wrong, with every failed figure (PnP agreement, too few verified matches)."""
    code, _, err = run_cli(["reconstruct", scene.a, scene.b, "-o", tmp_path / "scene.ply", "--backend", "neural",
                         "--weights", ckpts["mast3r"], "--accept-low-confidence",
                         "--report", tmp_path / "r.json"])  # fmt: skip
    assert code == 0, err
    pose = json.loads((tmp_path / "r.json").read_text())["pose"]
    assert pose["accepted_low_confidence"] is True and pose["confidence"] == 0.0
    assert any("agree with the PnP pose" in d for d in pose["doubts"])
    assert any(re.search(TOO_FEW_VERIFIED, d) for d in pose["doubts"])
    conf = load_cameras(tmp_path / "scene.cameras.json").pose_confidence
    assert conf is not None and conf["accepted_low_confidence"] is True and conf["doubts"] == pose["doubts"]
    assert "the pose may be wrong" in err


def test_noise_point_maps_are_refused(scene: Scene) -> None:
    """A stand-in network returning shape-correct noise: refused by the library too, naming the PnP figure."""
    with pytest.raises(ReconstructionError, match=r"confident pixels \(\d+ %\) agree with the PnP pose"):
        _neural(scene, NoiseBackbone())


def test_exact_point_maps_with_unrelated_descriptors_fail_the_verified_match_minimum(scene: Scene) -> None:
    """The PnP agrees (exact point maps) but the descriptors match nothing the point maps confirm: the classical
    minimum of verified matches (PoseConfig.min_inliers) refuses it; written, flagged, when accepted."""
    with pytest.raises(ReconstructionError, match=TOO_FEW_VERIFIED):
        _neural(scene, UnrelatedDescriptors(scene))
    rec = _neural(scene, UnrelatedDescriptors(scene), accept=True)
    conf = rec.cameras().pose_confidence
    assert conf is not None and conf["accepted_low_confidence"] is True and conf["score"] == 0.0
    assert len(rec.pose.geometry.inliers) < PoseConfig().min_inliers


def test_exact_point_maps_are_accepted(scene: Scene) -> None:
    """A sensible neural pose (the true point maps of the pair) passes the same acceptance without a doubt."""
    rec = _neural(scene, OracleBackbone(scene))
    pose = rec.pose
    assert pose is not None and pose.doubts == [] and not pose.accepted_low_confidence
    conf = pose.confidence
    assert conf is not None and conf.score > 0.5 and "refit_rotation_deg" in conf.checks
    # the same a contrario test as a classical pose, on the fused descriptors' matches (issue 25)
    assert conf.evidence is not None and conf.evidence.log10_nfa < -3 and rec.pose.geometry.source == "pointmap"
    assert syn.pose_errors(rec.pose.geometry.R, rec.pose.geometry.t, scene.R, scene.t)[0] < 0.05


def test_both_backends_call_the_one_acceptance(scene: Scene, monkeypatch: pytest.MonkeyPatch) -> None:
    """The classical and the neural pose go through the same function, once per run."""
    calls: list[str] = []

    class Accepted(Exception):
        pass

    def spy(v0: View, v1: View, geometry, pose, config, *, evidence=None):  # noqa: ANN001, ANN202
        calls.append(str(geometry.diagnostics.get("method", "essential")))
        raise Accepted

    monkeypatch.setattr(search_module, "accept_pose", spy)
    with pytest.raises(Accepted):
        Pipeline(ReconstructConfig(views=ViewConfig(size=SIZE[0]))).run([scene.a, scene.b])
    with pytest.raises(Accepted):
        _neural(scene, OracleBackbone(scene))
    assert calls == ["essential", "pnp-ransac"]


# ------------------------------------------------------------------------------ 2. degenerate matches, kept from OpenCV
W, H = 128, 96
K = np.array([[111.0, 0.0, 64.0], [0.0, 111.0, 48.0], [0.0, 0.0, 1.0]])
R_TRUE = cv2.Rodrigues(np.array([[0.0], [np.deg2rad(5.0)], [0.0]]))[0]
T = np.array([-0.4, 0.0, 0.02])  # camera 1 = R·X + T
T_TRUE = T / np.linalg.norm(T)


def _view(source: str) -> View:
    image, mask = np.zeros((H, W, 3), np.float32), np.ones((H, W), bool)
    return View("v", Path("v.png"), image, mask, K.copy(), (W, H), source)  # type: ignore[arg-type]


def _true_matches(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` correspondences of random points 3–8 units away, 5° of rotation, 0.05 px of noise. [n, 2] ×2"""
    X = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(3, 8, n)]
    p0, p1 = X @ K.T, (X @ R_TRUE.T + T) @ K.T
    xy0, xy1 = p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]
    return xy0 + rng.normal(0, 0.05, xy0.shape), xy1 + rng.normal(0, 0.05, xy1.shape)


def _matches(xy0: np.ndarray, xy1: np.ndarray) -> Matches:
    n = len(xy0)
    return Matches(xy0, xy1, np.ones(n, np.float32), np.arange(n), np.arange(n))


def _degenerate(case: str) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    if case in ("0", "4", "7"):
        return _true_matches(int(case), rng)
    if case == "one point x20":
        a, b = _true_matches(1, rng)
        return np.repeat(a, 20, 0), np.repeat(b, 20, 0)
    if case == "7 points x3":  # 21 matches: enough before, as long as repeats counted
        a, b = _true_matches(7, rng)
        return np.repeat(a, 3, 0), np.repeat(b, 3, 0)
    if case == "one line":  # every match on the row y = 10 of both photos
        a, b = _true_matches(40, rng)
        a[:, 1] = b[:, 1] = 10.0
        return a, b
    raise AssertionError(case)


@pytest.mark.parametrize("source", ["prior", "file"])
@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("0", r"only 0 matches survived filtering, need at least 15"),
        ("4", r"only 4 matches survived filtering, need at least 15"),
        ("7", r"only 7 matches survived filtering, need at least 15"),
        ("one point x20", r"only 1 match survived filtering \(20 with repeats\)"),
        ("7 points x3", r"only 7 matches survived filtering \(21 with repeats\)"),
        ("one line", r"lie along one line in photo 1"),
    ],
)
def test_pose_stage_refuses_degenerate_matches(case: str, message: str, source: str) -> None:
    """Too few, repeated or collinear matches: a ReconstructionError naming the count (before: a pose "verified"
    by 21 repeats of 7 matches, or one fitted to a line)."""
    with pytest.raises(ReconstructionError, match=message):
        estimate_pose(_view(source), _view(source), _matches(*_degenerate(case)))


@pytest.mark.parametrize("source", ["prior", "file"])
def test_pose_stage_refuses_non_finite_matches_with_a_typed_error(source: str) -> None:
    """NaN in a match: the typed NonFiniteError (an InputError, the contract of ``tests/test_stress.py``), never a
    ``cv2.error``."""
    a, b = _true_matches(40, np.random.default_rng(0))
    a[3, 0] = np.nan
    with pytest.raises(NonFiniteError, match="matches.xy0"):
        estimate_pose(_view(source), _view(source), _matches(a, b))


@pytest.mark.parametrize("seed", [23, 27, 94])
def test_repeated_matches_that_make_opencv_assert_still_give_the_pose(seed: int) -> None:
    """True correspondences with some of them repeated (as SIFT's orientations repeat a keypoint): OpenCV's USAC
    asserts ``!model.empty()`` on the fundamental matrix of the focal search (before: cv2.error, exit 1); the
    distinct matches are fitted instead and the pose comes out right."""
    rng = np.random.default_rng(seed)
    xy0, xy1 = _true_matches(int(rng.integers(30, 400)), rng)
    extra = rng.integers(0, len(xy0), int(rng.integers(0, len(xy0) // 3 + 1)))
    a, b = np.r_[xy0, xy0[extra]], np.r_[xy1, xy1[extra]]
    order = rng.permutation(len(a))
    g = estimate_pose(_view("prior"), _view("prior"), _matches(a[order], b[order]))
    rot, tdir = syn.pose_errors(g.R, g.t, R_TRUE, T_TRUE)
    assert rot < 0.5 and tdir < 5.0, (rot, tdir)


def test_opencv_fits_run_within_their_preconditions() -> None:
    """The guard of every robust fit: too few distinct points, NaN, mismatched lengths → no model; float32 and
    strided input → the float64 result; repeats take their original's inlier flag. Never a cv2.error."""
    rng = np.random.default_rng(0)
    a, b = _true_matches(60, rng)
    H0, m0 = find_homography(a, b, 1.5, 2000)
    assert H0 is not None and m0 is not None and m0.shape == (60,)
    for xa, xb in (
        (a[:3], b[:3]),  # below the 4 points of a homography
        (np.repeat(a[:3], 10, 0), np.repeat(b[:3], 10, 0)),  # 30 matches, 3 distinct
        (np.where(np.arange(60)[:, None] == 5, np.nan, a), b),  # a NaN
        (a, b[:59]),  # lengths differ
        (np.zeros((0, 2)), np.zeros((0, 2))),
    ):
        assert find_homography(xa, xb, 1.5, 2000) == (None, None)
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    H1, _ = find_homography(a32, b32, 1.5, 2000)
    np.testing.assert_array_equal(H1, find_homography(a32.astype(np.float64), b32.astype(np.float64), 1.5, 2000)[0])
    wide = np.repeat(a, 2, 1)[:, ::2]  # a strided view of a
    assert not wide.flags.c_contiguous
    np.testing.assert_array_equal(find_homography(wide, b, 1.5, 2000)[0], H0)

    def always_asserts_on_repeats(xa: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(np.unique(xa, axis=0)) < len(xa):
            raise cv2.error("(-215:Assertion failed) !model.empty()")
        return cv2.findHomography(xa, xb, cv2.USAC_MAGSAC, 1.5, maxIters=2000)

    rep0, rep1 = np.r_[a, a[:10]], np.r_[b, b[:10]]
    H2, m2 = robust_fit(always_asserts_on_repeats, rep0, rep1, 4, "test")
    assert H2 is not None and m2 is not None and m2.shape == (70,)
    np.testing.assert_array_equal(m2[60:], m2[:10])  # each repeat flagged as its first occurrence

    def always_asserts(xa: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise cv2.error("(-215:Assertion failed) !model.empty()")

    assert robust_fit(always_asserts, rep0, rep1, 4, "test") == (None, None)


@pytest.mark.parametrize("case", ["0 points", "5 points", "5 points x10", "one point x50", "one line", "NaN"])
def test_pnp_refuses_degenerate_point_maps(case: str) -> None:
    """The neural pose's PnP: too few distinct points, repeats, collinear 3-D points, NaN → ReconstructionError
    (before: a pose "explained" by 10 repeats of 5 points, or by 50 points on a line)."""
    rng = np.random.default_rng(0)
    n = {"0 points": 0, "5 points": 5, "5 points x10": 5, "one point x50": 1}.get(case, 50)
    X = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 4, n)]
    if case.endswith("x10") or case.endswith("x50"):
        X = np.repeat(X, 10 if case.endswith("x10") else 50, 0)
    if case == "one line":
        X[:, 1], X[:, 2] = 0.0, 3.0
    xy = (X @ K.T)[:, :2] / (X @ K.T)[:, 2:]
    if case == "NaN":
        X[:] = np.nan
    with pytest.raises(ReconstructionError, match="pose could not be estimated"):
        pose_from_pointmap(xy, X, K)


def test_cmyk_jpeg_pair_at_size_128_reconstructs(tmp_path: Path) -> None:
    """The reported pair: CMYK JPEGs of a textured synthetic room 5° apart (256×192), ``--size 128``. Before:
    exit 1, "internal error" (cv2.findFundamentalMat, !model.empty(), on 441 matches of which 396 distinct)."""
    from PIL import Image

    paths = []
    for k, image in enumerate(rendered_pair(PairSpec("room", 5, (256, 192))).images):
        rgb = np.rint(np.clip(image, 0, 1) * 255).astype(np.uint8)
        paths.append(tmp_path / f"view{k}.jpg")
        Image.fromarray(rgb).convert("CMYK").save(paths[-1], "JPEG")
    code, _, err = run_cli(["reconstruct", *paths, "-o", tmp_path / "s.ply", "--size", "128", "-q",
                         "--report", tmp_path / "r.json"])  # fmt: skip
    assert code == 0, err
    assert json.loads((tmp_path / "r.json").read_text())["pose"]["doubts"] == []
