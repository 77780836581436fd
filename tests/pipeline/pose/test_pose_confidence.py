"""The pose confidence (issue 14): checks independent of the RANSAC, and the refusal of doubtful poses.

Unit tests run :func:`assess_pose` on exact synthetic correspondences (no rendering, no SIFT): a correct pose is
trusted, a perturbed one is not, an unknown focal length on a wide object-centric orbit is flagged, a pose that is
all rotation and no parallax is flagged. The pipeline tests render small orbit pairs: doubts that the pose stage
puts in ``geometry.doubts`` are honoured, and ``macsplat reconstruct`` refuses a wrong wide pose with
exit code 3 and no file, or writes it with ``--accept-low-confidence`` and records the confidence in the report
and the cameras file.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.cameras import Camera, load_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.pose import (
    LOW_CONFIDENCE_HINT,
    PoseConfidence,
    PoseConfig,
    PoseSearchConfig,
    assess_pose,
    refit_pose,
)
from macsplat_cli.pipeline.pose.confidence import MIN_PARALLAX_TO_ROTATION
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, classical_stages
from macsplat_cli.pipeline.stages import EssentialPose
from macsplat_cli.pipeline.types import Matches, TwoViewGeometry, View
from macsplat_cli.pipeline.views import ViewConfig

from support.cli import run_cli
from support.scenes import PairFactory, PairSpec

W, H = 512, 384


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle, np.float64).reshape(3, 1))[0]


# ------------------------------------------------------------------------------ exact correspondences
def _orbit_geometry(
    angle: float, *, fov: float = 50.0, seed: int = 0, n: int = 400, noise_px: float = 0.3, kind: str = "object"
) -> tuple[TwoViewGeometry, Camera, Camera]:
    """The true relative pose of ``orbit_pair(kind, angle)`` with ``n`` noisy exact matches of random points
    around the point the two optical axes pass closest to (the orbit's target)."""
    cam0, cam1 = syn.orbit_pair(kind, angle, seed=seed, fov_deg=fov, width=W, height=H)  # type: ignore[arg-type]
    R, t = syn.relative_pose(cam0, cam1)
    # the closest point between the two optical axes (world frame)
    c0, c1 = cam0.center, cam1.center
    a0, a1 = cam0.cam_to_world[:3, 2], cam1.cam_to_world[:3, 2]
    M = np.stack([a0, -a1], 1)
    u = np.linalg.lstsq(M, c1 - c0, rcond=None)[0]
    target = 0.5 * (c0 + u[0] * a0 + c1 + u[1] * a1)
    radius = 0.3 * float(np.linalg.norm(target - c0))
    rng = np.random.default_rng(seed)
    X = target + rng.uniform(-radius, radius, (6 * n, 3))
    xy = []
    for cam in (cam0, cam1):
        Xc = X @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3]
        p = Xc @ cam.K.T
        xy.append(p[:, :2] / p[:, 2:3])
    inside = np.all([(q[:, 0] > 0) & (q[:, 0] < W) & (q[:, 1] > 0) & (q[:, 1] < H) for q in xy], axis=0)
    keep = np.flatnonzero(inside)[:n]
    xy0 = xy[0][keep] + rng.normal(0, noise_px, (len(keep), 2))
    xy1 = xy[1][keep] + rng.normal(0, noise_px, (len(keep), 2))
    idx = np.arange(len(keep))
    matches = Matches(xy0, xy1, np.ones(len(keep), np.float32), idx, idx, {"verified": len(keep)})
    x0 = np.c_[xy0, np.ones(len(keep))] @ np.linalg.inv(cam0.K).T
    x1 = np.c_[xy1, np.ones(len(keep))] @ np.linalg.inv(cam1.K).T
    parallax = np.degrees(np.arccos(np.clip(np.sum(
        (x0 @ R.T) / np.linalg.norm(x0, axis=1, keepdims=True) / np.linalg.norm(x1, axis=1, keepdims=True) * x1, 1
    ), -1, 1)))  # fmt: skip
    t_unit = t / np.linalg.norm(t)
    geometry = TwoViewGeometry(R, t_unit, cam0.K.copy(), cam1.K.copy(), matches)
    geometry.median_parallax_deg = float(np.median(parallax))
    return geometry, cam0, cam1


def _view(cam: Camera, source: str) -> View:
    return View(cam.name, Path(f"{cam.name}.png"), np.zeros((H, W, 3), np.float32), np.ones((H, W), bool),
                cam.K.copy(), (W, H), source)  # type: ignore[arg-type]  # fmt: skip


def _assess(geometry: TwoViewGeometry, cam0: Camera, cam1: Camera, source: str = "file") -> PoseConfidence:
    return assess_pose(_view(cam0, source), _view(cam1, source), geometry)


def test_correct_pose_with_known_intrinsics_is_trusted() -> None:
    """The true pose of a 60° orbit with exact matches: every check passes, fast, and the re-fit stays put."""
    geometry, cam0, cam1 = _orbit_geometry(60)
    conf = _assess(geometry, cam0, cam1)
    assert conf.ok, conf.reasons
    assert conf.score > 0.8
    assert conf.checks["refit_rotation_deg"] < 0.1
    assert conf.checks["parallax_to_rotation"] > 0.5
    assert "focal_rotation_deg" not in conf.checks  # the focal length was given
    assert conf.seconds < 1.0
    doc = conf.to_dict()
    assert json.loads(json.dumps(doc)) == doc and set(doc) == {"score", "ok", "reasons", "checks"}


@pytest.mark.parametrize("perturb_deg", [10.0, 20.0])
def test_perturbed_pose_is_not_trusted(perturb_deg: float) -> None:
    """The same matches with the rotation turned 10–20° away: the re-fit on its own matches moves it back."""
    geometry, cam0, cam1 = _orbit_geometry(60)
    axis = np.array([0.3, 1.0, -0.2])
    geometry.R = _rotation(axis / np.linalg.norm(axis) * math.radians(perturb_deg)) @ geometry.R
    conf = _assess(geometry, cam0, cam1)
    assert not conf.ok
    assert conf.score < 0.5
    assert conf.checks["refit_rotation_deg"] > 5.0
    assert any("re-fitted" in r for r in conf.reasons)


def test_refit_pose_recovers_the_true_rotation() -> None:
    """Gauss–Newton from a 5° perturbation converges to the true pose on exact matches."""
    geometry, _, _ = _orbit_geometry(45)
    R_true = geometry.R.copy()
    start = _rotation(np.array([0.0, math.radians(5.0), 0.0])) @ R_true
    fit = refit_pose(start, geometry.t, geometry.K0, geometry.K1, geometry.inliers.xy0, geometry.inliers.xy1)
    assert rotation_error_deg(fit.R, R_true) < 0.2
    assert np.median(np.abs(fit.residuals)) < 0.5
    assert np.linalg.norm(fit.t) == pytest.approx(1.0)


def test_unknown_focal_on_a_wide_object_orbit_is_flagged() -> None:
    """Both optical axes through the target (an object-centric pair) and no intrinsics: at 75° a ±10 % focal
    length fits the matches as well and turns the rotation by degrees: flagged, with the remedy. The same pose
    with the intrinsics given is trusted."""
    wide, cam0, cam1 = _orbit_geometry(75, kind="object")
    conf = _assess(wide, cam0, cam1, source="prior")
    assert not conf.ok
    assert conf.checks["focal_rotation_deg"] > 4.0
    assert any("focal length" in r and "--focal" in r for r in conf.reasons)
    # the same pose with the intrinsics given: the focal check does not apply
    assert _assess(wide, cam0, cam1, source="file").ok


def test_rotation_without_parallax_is_flagged() -> None:
    """A pose that is mostly rotation with little parallax (what a homography's matches give) is flagged."""
    geometry, cam0, cam1 = _orbit_geometry(60)
    geometry.median_parallax_deg = 3.0
    conf = _assess(geometry, cam0, cam1)
    assert not conf.ok
    assert conf.checks["parallax_to_rotation"] < MIN_PARALLAX_TO_ROTATION
    assert any("mostly rotation" in r for r in conf.reasons)


# ------------------------------------------------------------------------------ pipeline and CLI
@pytest.fixture(scope="module")
def pairs(pair_files: PairFactory) -> dict[str, tuple[Path, Path, Path]]:
    """Rendered orbit pairs: (photo a, photo b, cameras file with their true intrinsics), by name."""
    out = {}
    for name, kind, angle, fov, seed in [("easy", "room", 15, 50, 0), ("wide", "object", 60, 50, 1)]:
        files = pair_files(PairSpec(kind, angle, (W, H), fov, orbit_seed=seed))  # type: ignore[arg-type]
        out[name] = (files.a, files.b, files.cameras)
    return out


class _DoubtingPose:
    """The essential-matrix pose stage, then a doubt appended as a pose check would."""

    name = "test:doubting-essential"
    doubt = "the test pose stage doubts this pose"

    def __init__(self) -> None:
        self.inner = EssentialPose(PoseConfig())

    def __call__(self, v0: View, v1: View, matches: Matches, pair: object = None) -> TwoViewGeometry:
        geometry = self.inner(v0, v1, matches, pair)
        geometry.doubts.append(self.doubt)
        return geometry


def test_pose_stage_doubts_are_honoured(pairs: dict[str, tuple[Path, Path, Path]]) -> None:
    """A doubt in ``geometry.doubts`` refuses an otherwise good pair (one line, the hint); with
    ``accept_low_confidence`` the scene is built and the doubt recorded in the report and the cameras."""
    a, b, cams = pairs["easy"]
    views = ViewConfig(size=256, intrinsics=cams)
    config = ReconstructConfig(views=views)
    with pytest.raises(ReconstructionError) as err:
        Pipeline(config, classical_stages(config, pose=_DoubtingPose())).run([a, b])
    msg = str(err.value)
    assert msg.startswith(_DoubtingPose.doubt) and msg.endswith(f"({LOW_CONFIDENCE_HINT})") and "\n" not in msg
    assert err.value.exit_code == 3

    accepting = ReconstructConfig(views=views, search=PoseSearchConfig(accept_low_confidence=True))
    rec = Pipeline(accepting, classical_stages(accepting, pose=_DoubtingPose())).run([a, b])
    assert rec.report.pose["doubts"] == [_DoubtingPose.doubt]
    assert rec.report.pose["accepted_low_confidence"] is True
    assert rec.report.pose["confidence"] > 0.5  # the independent checks themselves trust the pose
    pc = rec.cameras().pose_confidence
    assert pc is not None and pc["doubts"] == [_DoubtingPose.doubt] and pc["accepted_low_confidence"] is True
    assert rec.pose is not None and [(d.check, d.message) for d in rec.pose.doubts] == [("pose", _DoubtingPose.doubt)]


def test_cli_good_pair_is_accepted_with_its_confidence(
    pairs: dict[str, tuple[Path, Path, Path]], tmp_path: Path
) -> None:
    """A 15° room pair, no intrinsics: exit 0, the confidence high in the report, the summary and the cameras."""
    a, b, _ = pairs["easy"]
    out = tmp_path / "scene.ply"
    code, _, err = run_cli(["reconstruct", a, b, "-o", out, "--size", "256", "--report", tmp_path / "r.json"])
    assert code == 0, err
    pose = json.loads((tmp_path / "r.json").read_text())["pose"]
    assert pose["confidence"] > 0.5 and pose["doubts"] == [] and "focal_rotation_deg" in pose["confidence_checks"]
    cams = load_cameras(tmp_path / "scene.cameras.json")
    assert cams.pose_confidence is not None and cams.pose_confidence["score"] == pytest.approx(pose["confidence"])
    assert cams.pose_confidence["accepted_low_confidence"] is False
    assert "pose check" in err and "confidence" in err
    assert re.search(r"\d+ of \d+ putative matches \(primary tier\), log10 NFA -\d+", err), err
    # what the acceptance weighed (issue 25): the tier's putative matches, the NFA, the rule
    ev = pose["evidence"]
    assert ev["tier"] == "primary" and ev["failed"] == [] and ev["log10_nfa"] < -3
    assert 0 < ev["inliers"] <= ev["putative_matches"] and 0 < ev["coverage"] <= 1
    assert 3 * ev["rotation_sigma_deg"] < 2 and "log10 NFA below -3" in ev["rule"]
    assert cams.pose_confidence["log10_nfa"] == pytest.approx(ev["log10_nfa"])
    assert cams.pose_confidence["acceptance_rule"] == ev["rule"]


def test_cli_refuses_a_wrong_wide_pose_and_writes_it_on_request(
    pairs: dict[str, tuple[Path, Path, Path]], tmp_path: Path
) -> None:
    """Object orbit, 60°, 50° field of view, no intrinsics: the pose the matches give is 9° off (the focal
    length is not observable). Refused: exit 3, one error line with the hint, no file. With
    ``--accept-low-confidence``: written, a warning, and the low confidence in the report and the cameras."""
    a, b, _ = pairs["wide"]
    out = tmp_path / "scene.ply"
    code, _, err = run_cli(["reconstruct", a, b, "-o", out, "-q"])
    assert code == 3
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "--accept-low-confidence" in lines[0]
    assert not any(tmp_path.iterdir())  # no scene, no cameras, no temporary file

    report = tmp_path / "report.json"
    code, _, err = run_cli(
        ["reconstruct", a, b, "-o", out, "--accept-low-confidence", "--report", report, "--size", "256"]
    )
    assert code == 0, err
    assert out.is_file()
    assert "warning" in err.lower() and "pose may be wrong" in err
    pose = json.loads(report.read_text())["pose"]
    assert pose["accepted_low_confidence"] is True and pose["doubts"]
    assert pose["confidence"] < 0.5  # the independent checks agree with the doubt
    cams = load_cameras(tmp_path / "scene.cameras.json")
    assert cams.pose_confidence is not None and cams.pose_confidence["accepted_low_confidence"] is True
    assert cams.pose_confidence["score"] == pytest.approx(pose["confidence"])
