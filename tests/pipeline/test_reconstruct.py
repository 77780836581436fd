"""``macsplat reconstruct`` and the two-view pipeline on ray-traced pairs with exact ground truth.

Accuracy (pose, focal length, depth) at several baselines, the command end to end, every
kind of bad input (one ``error:`` line, the right exit code, no files left behind), and
the library API (cameras at both resolutions, backend names, a custom stage backend).

Every synthetic pair is rendered once per module and saved as PNG; the errors measured by
the accuracy tests are printed as a table at the end of the module (``pytest -s``).
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from macsplat_cli.cameras import Camera, CameraSet, load_cameras, save_cameras
from macsplat_cli.cli import main
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.engine import reconstruct
from macsplat_cli.errors import InputError, ReconstructionError, SameViewError
from macsplat_cli.images import save_image
from macsplat_cli.pipeline.pose import PoseConfig
from macsplat_cli.pipeline.run import STAGES, Pipeline, ReconstructConfig, Reconstruction, classical_stages
from macsplat_cli.pipeline.stages import EssentialPose
from macsplat_cli.pipeline.types import Matches, TwoViewGeometry, View
from macsplat_cli.pipeline.views import ViewConfig, prior_focal
from macsplat_cli.ply import read_ply

from support.cli import run_cli
from support.scenes import PairFactory, PairSpec

# ------------------------------------------------------------------------------ bounds
# Synthetic cameras: 512×384 px. With known intrinsics, the orbit_pair default 60° field of
# view; without, 50°, deliberately not the pipeline's 60° prior, so the focal length has to be
# estimated.
SIZE = (512, 384)
FOV_DEG = 60.0
UNKNOWN_FOV_DEG = 50.0
# Known intrinsics, orbit angle → (rotation error, translation-direction error) bounds in
# degrees. Measured when written: ≤ 0.22° rotation, ≤ 0.2° translation direction; the 75°
# pairs keep only a few hundred verified matches, hence the looser bound there.
POSE_TOL_DEG = {5: (0.5, 1.0), 20: (0.5, 1.0), 45: (0.5, 1.0), 75: (1.5, 3.0)}
# Unknown intrinsics (focal length self-calibrated from the matches), orbit angle →
# (rotation error in degrees, relative focal-length error). Measured: ≤ 0.46°, ≤ 2.1 %.
UNKNOWN_TOL = {10: (1.0, 0.03), 30: (1.0, 0.03)}
UNKNOWN_TDIR_TOL_DEG = 2.0  # measured ≤ 0.35°
# Median relative depth error of view 0 on the pixels the depth stage measured (not
# propagated), against the ray-traced depth divided by the true baseline. Measured ≤ 1 % up
# to 45°. Not bounded at 75°: there many "measured" background pixels are far too near
# (object scene: median error ~40 %); the number is still printed in the table.
DEPTH_TOL = {5: 0.03, 20: 0.03, 45: 0.03}
CLI_SIZE = (640, 480)  # the CLI pair is larger than the 512 px working size
CLI_WORK_SIZE = (256, 192)  # the end-to-end run uses --size 256 (a quarter of the pixels to splat and render)
MIN_GAUSSIANS = 10_000
U64 = np.finfo(np.float64).eps / 2
# float64 intrinsics rescaled between sizes: two roundings a side (the library's and the test's), 4u relative; a
# rescale and back, 8u
K_RTOL = 4 * U64


def _orthogonality(R: np.ndarray) -> float:
    """max |RRᵀ − I|: the estimated rotation's own defect, which enters every check through R."""
    return float(np.abs(R @ R.T - np.eye(3)).max())


# ------------------------------------------------------------------------------ data
@dataclass(frozen=True)
class Pair:
    """Two rendered views with their ground truth."""

    a: Path
    b: Path
    cam0: Camera
    cam1: Camera
    depth0: np.ndarray  # ray-traced depth of view 0 at the rendered size [H, W]
    intrinsics: Path  # cameras file holding the two true cameras (named after the files)

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.cam0.center - self.cam1.center))


MakePair = Callable[..., Pair]


@pytest.fixture(scope="module")
def make_pair(pair_files: PairFactory) -> MakePair:
    """``orbit_pair(kind, angle)`` (or ``pure_rotation_pair``) rendered once per session (``support.scenes``)."""

    def get(
        kind: str,
        angle: float,
        *,
        fov: float = FOV_DEG,
        size: tuple[int, int] = SIZE,
        textured: bool = True,
        rotation: bool = False,
    ) -> Pair:
        spec = PairSpec(kind, angle, size, fov, textured=textured, rotation=rotation)  # type: ignore[arg-type]
        files = pair_files(spec, ("view0.png", "view1.png"))
        cam0, cam1 = files.rendered.cams
        return Pair(files.a, files.b, cam0, cam1, files.rendered.depths[0], files.cameras)

    return get


@pytest.fixture(scope="module")
def error_table() -> Iterator[list[tuple]]:
    """Rows of measured errors; printed as a table after the module's last test (``-s``)."""
    rows: list[tuple] = []
    yield rows
    if rows:
        head = ("scene", "angle", "fov", "K", "rot °", "t dir °", "focal %", "depth %", "measured", "verified")
        print("\n\nsynthetic two-view errors (512x384; depth: median |rel| on the measured pixels of view 0)")
        print(" ".join(f"{h:>9}" for h in head))
        for r in sorted(rows, key=lambda r: (r[3], r[2], r[0], r[1])):
            print(" ".join(f"{v:>9.3f}" if isinstance(v, float) else f"{v!s:>9}" for v in r))


def _pose_errors(rec: Reconstruction, pair: Pair) -> tuple[float, float]:
    R_gt, t_gt = syn.relative_pose(pair.cam0, pair.cam1)
    return syn.pose_errors(rec.pose.geometry.R, rec.pose.geometry.t, R_gt, t_gt)


def _depth_error(rec: Reconstruction, pair: Pair) -> tuple[float, float]:
    """(median relative depth error, fraction of pixels compared) on view 0's measured pixels."""
    d = rec.depths[0]
    h, w = d.depth.shape
    gt = cv2.resize(pair.depth0, (w, h), interpolation=cv2.INTER_NEAREST) / pair.baseline  # reconstruction: baseline 1
    measured = d.measured if d.measured is not None else d.valid
    sel = measured & d.valid & (gt > 0)
    assert sel.mean() > 0.05, "the depth stage measured almost nothing"
    return float(np.median(np.abs(d.depth[sel] / gt[sel] - 1.0))), float(sel.mean())


def _run_pipeline(pair: Pair, *, intrinsics: bool) -> Reconstruction:
    config = ReconstructConfig(views=ViewConfig(intrinsics=pair.intrinsics if intrinsics else None))
    return Pipeline(config).run([pair.a, pair.b])


# ------------------------------------------------------------------------------ accuracy
@pytest.mark.parametrize(
    ("kind", "angle", "fov"),
    [(kind, angle, FOV_DEG) for kind in ("room", "object") for angle in sorted(POSE_TOL_DEG)],
)
def test_pose_and_depth_accuracy_with_known_intrinsics(
    make_pair: MakePair, error_table: list[tuple], kind: str, angle: int, fov: float
) -> None:
    """Rotation, translation direction and depth of orbit pairs are within the stated bounds."""
    pair = make_pair(kind, angle, fov=fov)
    rec = _run_pipeline(pair, intrinsics=True)
    rot_err, t_err = _pose_errors(rec, pair)
    depth_err, measured = _depth_error(rec, pair)
    error_table.append(
        (
            kind,
            angle,
            f"{fov:g}",
            "file",
            rot_err,
            t_err,
            0.0,
            100 * depth_err,
            measured,
            rec.report.matches["verified"],
        )
    )
    assert [im.intrinsics_source for im in rec.report.images] == ["file", "file"]
    np.testing.assert_allclose(rec.pose.geometry.K0, pair.cam0.rescaled(*SIZE).K, rtol=K_RTOL, atol=0)  # the file's K
    rot_tol, t_tol = POSE_TOL_DEG[angle]
    assert rot_err < rot_tol, f"rotation error {rot_err:.3f}°"
    assert t_err < t_tol, f"translation-direction error {t_err:.3f}°"
    assert np.linalg.norm(rec.pose.geometry.t) == pytest.approx(1.0, rel=0, abs=7 * U64)  # normalised (4u), the norm 3u
    if angle in DEPTH_TOL:
        assert depth_err < DEPTH_TOL[angle], f"median relative depth error {100 * depth_err:.2f} %"


def test_near_planar_wide_pair_is_resolved_not_wrong(make_pair: MakePair) -> None:
    """Room, 75° orbit, 50° field of view: the confident matches lie almost all on one wall, seen
    at a grazing angle. The essential matrix then picked a pose 11.8° / 10° off, which guided
    matching went on to 'verify' with 208 matches (67 correct). Two poses from the wall's
    homography explain the matches (39 and 40 of 40): the pair was refused as ambiguous. Issue 14:
    the wall's second pose puts part of the matches behind a camera, so the pair is resolved
    (measured 1.33° / 0.75°) — never a wrong pose. Issue 25: the evidence gathered before the pose (146 putative
    matches, 127 of them on 4 % of the photo, 89 % on the wall's homography) leaves the rotation uncertain by
    ±2.1° (3σ), over the ±2° an accepted pose needs; the later tiers find no better-supported pose, so the pair is
    refused naming that figure — written with --accept-low-confidence, and then still right."""
    pair = make_pair("room", 75, fov=UNKNOWN_FOV_DEG)
    with pytest.raises(
        ReconstructionError,
        match=r"cover \d+ % of the photo and leave its rotation uncertain.*lie on one plane\); a pose needs ±2°",
    ):
        _run_pipeline(pair, intrinsics=True)
    config = ReconstructConfig(views=ViewConfig(intrinsics=pair.intrinsics))
    config.search.accept_low_confidence = True
    rec = Pipeline(config).run([pair.a, pair.b])
    assert rec.pose is not None and rec.pose.accepted_low_confidence
    rot_err, t_err = _pose_errors(rec, pair)
    assert rot_err < POSE_TOL_DEG[75][0] and t_err < POSE_TOL_DEG[75][1]


@pytest.mark.parametrize("angle", sorted(UNKNOWN_TOL))
@pytest.mark.parametrize("kind", ["room", "object"])
def test_focal_self_calibration_with_unknown_intrinsics(
    make_pair: MakePair, error_table: list[tuple], kind: str, angle: int
) -> None:
    """Without intrinsics the focal length is estimated within 3 % and the pose stays accurate."""
    pair = make_pair(kind, angle, fov=UNKNOWN_FOV_DEG)
    rec = _run_pipeline(pair, intrinsics=False)
    rot_err, t_err = _pose_errors(rec, pair)
    w, h = rec.views[0].width, rec.views[0].height
    f_true = pair.cam0.rescaled(w, h).K[0, 0]
    f_errs = [abs(K[0, 0] / f_true - 1.0) for K in (rec.pose.geometry.K0, rec.pose.geometry.K1)]
    depth_err, measured = _depth_error(rec, pair)
    error_table.append(
        (kind, angle, f"{UNKNOWN_FOV_DEG:g}", "unknown", rot_err, t_err, 100 * max(f_errs), 100 * depth_err, measured,
         rec.report.matches["verified"])
    )  # fmt: skip
    assert abs(prior_focal(*SIZE) / f_true - 1.0) > 0.15  # the prior alone would be far off
    assert [im.intrinsics_source for im in rec.report.images] == ["estimated", "estimated"]
    rot_tol, f_tol = UNKNOWN_TOL[angle]
    assert max(f_errs) < f_tol, f"focal errors {f_errs}"
    assert rec.report.images[0].focal_px_working == pytest.approx(rec.pose.geometry.K0[0, 0], rel=K_RTOL, abs=0)
    assert rot_err < rot_tol, f"rotation error {rot_err:.3f}°"
    assert t_err < UNKNOWN_TDIR_TOL_DEG, f"translation-direction error {t_err:.3f}°"


# ------------------------------------------------------------------------------ CLI end to end
@dataclass(frozen=True)
class CliRun:
    code: int
    out: str
    err: str
    folder: Path
    pair: Pair


@pytest.fixture(scope="module")
def cli_pair(make_pair: MakePair) -> Pair:
    """A 640×480 room pair 15° apart, larger than the working images (512×384 by default)."""
    return make_pair("room", 15, fov=UNKNOWN_FOV_DEG, size=CLI_SIZE)


@pytest.fixture(scope="module")
def cli_run(cli_pair: Pair, tmp_path_factory: pytest.TempPathFactory) -> CliRun:
    """One full ``macsplat reconstruct`` run with every output."""
    out = tmp_path_factory.mktemp("cli") / "out"
    out.mkdir()
    code, stdout, stderr = run_cli(
        ["reconstruct", cli_pair.a, cli_pair.b, "-o", out / "scene.ply", "--renders", out / "views",
         "--num-renders", "4", "--video", out / "path.gif", "--report", out / "report.json",
         "--size", str(CLI_WORK_SIZE[0])]
    )  # fmt: skip
    return CliRun(code, stdout, stderr, out, cli_pair)


def test_cli_exits_0_and_prints_a_summary(cli_run: CliRun) -> None:
    """A successful run exits 0, prints nothing on stdout and a summary table on stderr."""
    assert cli_run.code == 0, cli_run.err
    assert cli_run.out == ""
    assert "macsplat reconstruct" in cli_run.err and "Gaussians" in cli_run.err
    assert "error:" not in cli_run.err and "Traceback" not in cli_run.err
    assert sorted(p.name for p in cli_run.folder.iterdir()) == sorted(
        ["scene.ply", "scene.cameras.json", "views", "path.gif", "report.json"]
    )  # nothing else, no temporary files


def test_summary_names_the_descriptors_that_gave_the_pose(cli_run: CliRun) -> None:
    """The summary's matches row names the fallback or the wide-baseline tier when their matches were kept."""
    from macsplat_cli.cli._summary import _matches_line
    from macsplat_cli.report import RunReport

    doc = json.loads((cli_run.folder / "report.json").read_text())
    report = RunReport(doc["macsplat_version"], doc["inputs"], doc["backends"], doc["times_s"], [], doc["keypoints"],
                       doc["fallback_used"], doc["matches"], doc["inlier_ratio"], doc["pose"], doc["depth_coverage"],
                       doc["depth_measured"], doc["gaussians"], {})  # fmt: skip
    plain = _matches_line(report, report.pose)
    assert "verified" in plain and "(" not in plain  # an easy pair: the first descriptors
    assert plain.split(" → ")[0] in cli_run.err  # the row as printed (long rows wrap in the table)
    fell_back = dataclasses.replace(report, fallback_used=True)
    fallback = _matches_line(fell_back, report.pose)
    assert fallback.startswith(plain) and "affine-simulated fallback" in fallback
    for tier, words in (("wide", "wide-baseline tier"), ("wide+plane-tiebreak", "plane's two poses")):
        line = _matches_line(fell_back, {**report.pose, "descriptors_tier": tier})
        assert line.startswith(plain) and words in line


def test_cli_scene_ply_reads_back(cli_run: CliRun) -> None:
    """The PLY reads back, finite, with as many Gaussians as the report says were written."""
    g = read_ply(cli_run.folder / "scene.ply")
    assert len(g) > MIN_GAUSSIANS
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.isfinite(getattr(g, name)).all(), name
    report = json.loads((cli_run.folder / "report.json").read_text())
    assert report["gaussians_written"] == len(g)
    # in front of camera 0, and no farther than the room's far wall at the scale of a unit baseline
    z = g.means[:, 2].double()
    far = float(cli_run.pair.depth0.max()) / cli_run.pair.baseline
    assert (z > 0).double().mean() > 0.99
    assert 0.0 < float(z.quantile(0.5)) < float(z.quantile(0.99)) < 1.2 * far


def test_cli_cameras_file(cli_run: CliRun) -> None:
    """The cameras file: 2 cameras at the photos' size, camera 0 the world, a unit baseline."""
    cams = load_cameras(cli_run.folder / "scene.cameras.json")
    assert len(cams) == 2
    assert cams.world == "camera_0" and cams.scale == "relative"
    assert [(c.width, c.height) for c in cams] == [CLI_SIZE, CLI_SIZE]
    np.testing.assert_array_equal(cams[0].cam_to_world, np.eye(4))
    # the centre −Rᵀt of a unit t: ‖t‖ to 7u, Rᵀ's orthogonality defect, a 3-term product (γ₃)
    R = cams[1].world_to_cam[:3, :3]
    tol = 7 * U64 + 3 * _orthogonality(R) + 2 * 3 * U64
    assert np.linalg.norm(cams[1].center) == pytest.approx(1.0, rel=0, abs=tol)
    pair = cli_run.pair
    T = cams[1].world_to_cam  # camera 0 is the world: this is the relative pose
    rot_err, t_err = syn.pose_errors(T[:3, :3], T[:3, 3], *syn.relative_pose(pair.cam0, pair.cam1))
    assert rot_err < 1.0 and t_err < 2.0, (rot_err, t_err)
    for cam, true in zip(cams, (pair.cam0, pair.cam1)):  # the focal, estimated, at the original size
        assert cam.K[0, 0] == pytest.approx(true.K[0, 0], rel=0.03)  # (d) as UNKNOWN_TOL: measured ≤ 2.1 %
        # the centre, rescaled from the working size: binary-exact here, and at worst K_RTOL
        assert cam.K[0, 2] == pytest.approx(CLI_SIZE[0] / 2, rel=K_RTOL, abs=0)
        assert cam.K[1, 2] == pytest.approx(CLI_SIZE[1] / 2, rel=K_RTOL, abs=0)


def test_cli_renders_and_video(cli_run: CliRun) -> None:
    """--renders writes N PNG views at the working size, --video a gif with N frames."""
    from PIL import Image

    views = sorted((cli_run.folder / "views").iterdir())
    assert [p.name for p in views] == [f"view_{i:03d}.png" for i in range(4)]
    report = json.loads((cli_run.folder / "report.json").read_text())
    w, h = report["images"][0]["working_size"]
    assert (w, h) == CLI_WORK_SIZE
    imgs = [cv2.imread(str(p)) for p in views]
    assert all(im is not None and im.shape == (h, w, 3) for im in imgs)
    assert all(im.mean() > 20 for im in imgs)  # the scene is visible, not a black frame
    assert np.abs(imgs[0].astype(int) - imgs[-1].astype(int)).mean() > 5  # the path moves
    with Image.open(cli_run.folder / "path.gif") as gif:
        assert gif.n_frames == 4 and gif.size == (w, h)


def test_cli_report_contents(cli_run: CliRun) -> None:
    """The report has stage times, keypoints, match counts, inlier ratio, outputs, intrinsics sources."""
    r = json.loads((cli_run.folder / "report.json").read_text())
    times = r["times_s"]
    for stage in STAGES:
        assert times[stage] > 0, stage
    stage_sum = sum(times[s] for s in STAGES)
    assert times["total"] >= stage_sum * (1 - len(STAGES) * 2 * U64)  # the test's own float sum: γₙ of it
    assert len(r["keypoints"]) == 2 and all(isinstance(k, int) and k > 100 for k in r["keypoints"])
    m = r["matches"]
    assert {"reciprocal", "confident", "verified"} <= set(m)
    assert m["reciprocal"] >= m["confident"] > 0 and m["verified"] > 100
    assert m["verified"] <= max(v for k, v in m.items() if k != "verified")
    assert 0 < r["inlier_ratio"] <= 1
    assert r["gaussians_written"] == r["gaussians"] > MIN_GAUSSIANS
    assert [im["intrinsics_source"] for im in r["images"]] == ["estimated", "estimated"]
    assert [im["original_size"] for im in r["images"]] == [list(CLI_SIZE)] * 2
    assert [im["working_size"] for im in r["images"]] == [list(CLI_WORK_SIZE)] * 2
    assert set(r["backends"]) >= set(STAGES)
    assert r["inputs"] == [str(cli_run.pair.a), str(cli_run.pair.b)]
    out = cli_run.folder
    assert r["outputs"] == {
        "scene": str(out / "scene.ply"),
        "cameras": str(out / "scene.cameras.json"),
        "renders": str(out / "views"),
        "video": str(out / "path.gif"),
    }


def test_cli_json_stdout_and_quiet(capsys: pytest.CaptureFixture[str], cli_pair: Pair, tmp_path: Path) -> None:
    """--json prints the report (the one --report writes) as valid JSON; -q leaves stderr empty."""
    code = main(
        ["reconstruct", str(cli_pair.a), str(cli_pair.b), "-o", str(tmp_path / "s.ply"), "--cameras",
         str(tmp_path / "cams.json"), "--report", str(tmp_path / "r.json"), "--json", "-q", "--size", "256"]
    )  # fmt: skip
    out, err = capsys.readouterr()
    assert code == 0, err
    assert err == ""
    printed = json.loads(out)
    assert printed == json.loads((tmp_path / "r.json").read_text())
    assert printed["outputs"] == {"scene": str(tmp_path / "s.ply"), "cameras": str(tmp_path / "cams.json")}
    assert len(load_cameras(tmp_path / "cams.json")) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cams.json", "r.json", "s.ply"]


def test_reconstruct_help_lists_the_options(capsys: pytest.CaptureFixture[str]) -> None:
    """``macsplat reconstruct --help`` exits 0 and documents every option."""
    code = main(["reconstruct", "--help"])
    out = capsys.readouterr().out
    assert code == 0 and "Usage" in out
    for opt in ("--output", "-o", "--cameras", "--renders", "--num-renders", "--video", "--report", "--json",
                "--size", "--intrinsics", "--focal", "--conf-threshold", "--quiet", "--verbose"):  # fmt: skip
        assert opt in out, opt


# ------------------------------------------------------------------------------ bad input
@pytest.fixture(scope="module")
def bad_files(make_pair: MakePair, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Named input files for the failure cases (all small or derived from cached renders)."""
    root = tmp_path_factory.mktemp("bad")
    good = make_pair("room", 20)
    room = syn.make_scene("room", 0)
    files = {"a": good.a, "b": good.b}
    # the same camera centre area, looking at the opposite wall: no common surface point
    away = good.cam0.center + (good.cam0.center - room.target)
    opposite = syn.look_at_camera("opp", good.cam0.center + [0.3, 0.0, 0.3], away)
    files["opposite"] = save_image(root / "opposite.png", syn.render(room, opposite).image)
    other = syn.orbit_pair("object", 0.0, seed=1)[0]
    files["other_scene"] = save_image(root / "other_scene.png", syn.render(syn.make_scene("object", 1), other).image)
    flat = make_pair("room", 20, textured=False)
    files["flat_a"], files["flat_b"] = flat.a, flat.b
    rot = make_pair("room", 15, rotation=True)
    files["rot_a"], files["rot_b"] = rot.a, rot.b
    a, b = cv2.imread(str(good.a)), cv2.imread(str(good.b))
    cv2.imwrite(str(root / "crop_a.png"), a[150:222, 200:272])  # 72×72: a few keypoints, a few matches
    cv2.imwrite(str(root / "crop_b.png"), b[150:222, 200:272])
    cv2.imwrite(str(root / "tiny.png"), a[:48, :60])
    files.update({k: root / f"{k}.png" for k in ("crop_a", "crop_b", "tiny")})
    files["junk"] = root / "junk.jpg"
    files["junk"].write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    files["missing"] = root / "missing.png"
    files["square_cams"] = root / "square_cams.json"
    K = np.array([[400.0, 0.0, 200.0], [0.0, 400.0, 200.0], [0.0, 0.0, 1.0]])
    save_cameras(files["square_cams"], CameraSet([Camera("sq", 400, 400, K, np.eye(4))]))
    return files


@pytest.mark.parametrize(
    ("images", "extra", "code", "pattern"),
    [
        pytest.param(("a", "a"), (), 3, r"same view", id="same-image-twice"),
        pytest.param(("a", "opposite"), (), 3, r"\d+ .*need at least \d+", id="no-overlap-opposite-wall"),
        pytest.param(
            ("a", "other_scene"),
            (),
            3,
            r"",
            id="no-overlap-two-scenes",
        ),
        pytest.param(
            ("flat_a", "flat_b"),
            (),
            3,
            r"",
            id="textureless",
        ),
        pytest.param(
            ("crop_a", "crop_b"),
            (),
            3,
            r"\d+ .*need at least \d+",
            id="too-few-matches",
        ),
        pytest.param(
            ("crop_a", "crop_b"),
            ("--conf-threshold", "0.04"),
            3,
            r"\d+ .*need at least \d+",
            id="too-few-matches-library-tau",
        ),
        pytest.param(("rot_a", "rot_b"), (), 3, r"no baseline", id="pure-rotation"),
        pytest.param(("tiny", "b"), (), 2, r"tiny\.png.*too small", id="tiny-image"),
        pytest.param(("a", "junk"), (), 2, r"junk\.jpg", id="corrupt-file"),
        pytest.param(("missing", "b"), (), 2, r"missing\.png", id="missing-file"),
        pytest.param(
            ("a", "b"),
            ("--intrinsics", "square_cams"),
            2,
            r"square_cams\.json.*do not fit",
            id="intrinsics-wrong-aspect",
        ),
        pytest.param(("a", "b"), ("--focal", "-3"), 2, r"--focal", id="negative-focal"),
        pytest.param(("a", "b"), ("--budget", "0"), 2, r"--budget", id="budget-zero"),
        pytest.param(("a", "b"), ("--budget", "-4"), 2, r"--budget", id="budget-negative"),
        pytest.param(("a", "b"), ("--budget", "many"), 2, r"--budget.*integer", id="budget-not-a-number"),
        pytest.param(("a", "b"), ("--quality", "ultra"), 2, r"--quality 'ultra'", id="unknown-quality"),
    ],
)
def test_bad_input_one_error_line_exit_code_no_files(
    capsys: pytest.CaptureFixture[str],
    bad_files: dict[str, Path],
    tmp_path: Path,
    images: tuple[str, str],
    extra: tuple[str, ...],
    code: int,
    pattern: str,
) -> None:
    """Bad or unreconstructable input: one ``error:`` line, exit 2 or 3, no output or temporary files."""
    inputs_before = sorted(p for f in bad_files.values() for p in f.parent.iterdir())
    args = ["reconstruct", *(bad_files[k] for k in images), "-o", tmp_path / "scene.ply", "--renders",
            tmp_path / "views", "--num-renders", "2", "--video", tmp_path / "path.gif", "--report",
            tmp_path / "report.json", "-q",
            *(str(bad_files.get(x, x)) for x in extra)]  # fmt: skip
    got = main([str(a) for a in args])
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert got == code, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and out == ""
    assert re.search(pattern, lines[0]), lines[0]
    assert sorted(tmp_path.rglob("*")) == []  # no output, partial or temporary file
    assert sorted(p for f in bad_files.values() for p in f.parent.iterdir()) == inputs_before


def test_same_view_stops_the_pose_search_at_the_primary_tier(bad_files: dict[str, Path]) -> None:
    """Two photos of one view: the primary tier's matches have not moved, which no other tier's matches can change,
    so the fallback, wide, plane tie-break and learned tiers do not run (they took ~25 s to say the same)."""
    events: list[tuple[str, str]] = []
    with pytest.raises(SameViewError, match="same view"):
        reconstruct([bad_files["a"], bad_files["a"]], on_stage=lambda s, e: events.append((s, e)))
    stages = [s for s, e in events if e == "start"]
    assert "pose" in stages and ("pose", "fail") in events
    assert not [s for s in stages if "(" in s], stages  # no "descriptors (fallback)", "pose (wide)", ...


@pytest.mark.parametrize(
    ("images", "extra", "code", "failed_stage"),
    [(("missing", "b"), (), 2, "images"), (("crop_a", "crop_b"), ("--conf-threshold", "0.04"), 3, "pose")],
    ids=["input-error", "reconstruction-error"],
)
def test_failure_without_quiet_ends_with_the_error_line(
    capsys: pytest.CaptureFixture[str],
    bad_files: dict[str, Path],
    tmp_path: Path,
    images: tuple[str, str],
    extra: tuple[str, ...],
    code: int,
    failed_stage: str,
) -> None:
    """Without -q the progress lines mark the failed stage and the one ``error:`` line comes last."""
    got = main(["reconstruct", *(str(bad_files[k]) for k in images), "-o", str(tmp_path / "scene.ply"), *extra])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert got == code, err
    assert lines[-1].startswith("error: ") and sum("error:" in ln for ln in lines) == 1, err
    assert any(failed_stage in ln and "failed" in ln for ln in lines), err
    assert "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("extra", "pattern"),
    [
        pytest.param(("-o", "{tmp}/scene.txt"), r"\.ply", id="not-ply"),
        pytest.param(("-o", "{tmp}/blocker/scene.ply"), r"blocker", id="output-under-a-file"),
        pytest.param(
            ("-o", "{tmp}/scene.ply", "--cameras", "{tmp}/blocker/c.json"), r"blocker", id="cameras-under-a-file"
        ),
        pytest.param(("-o", "{tmp}/scene.ply", "--renders", "{tmp}/blocker"), r"not a folder", id="renders-is-a-file"),
        pytest.param(("-o", "{tmp}/scene.ply", "--video", "{tmp}/v.avi"), r"video format", id="bad-video-format"),
        pytest.param(("-o", "{tmp}/scene.ply", "--report", "{tmp}/scene.ply"), r"same file", id="two-outputs-one-file"),
        pytest.param(("-o", "{tmp}/scene.ply", "--num-renders", "1"), r"num-renders", id="one-render"),
        pytest.param(("-o", "{tmp}/scene.ply", "--size", "32"), r"size", id="size-too-small"),
        pytest.param((), r"--output", id="no-output"),
    ],
)
def test_bad_output_options_fail_before_any_work(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    bad_files: dict[str, Path],
    tmp_path: Path,
    extra: tuple[str, ...],
    pattern: str,
) -> None:
    """Unwritable or invalid outputs and options: exit 2 with one line, before the pipeline runs."""
    calls: list[object] = []
    monkeypatch.setattr(Pipeline, "run", lambda self, *a, **k: calls.append(a))
    (tmp_path / "blocker").write_text("a file where a folder is expected")
    args = [x.replace("{tmp}", str(tmp_path)) for x in extra]
    got = main(["reconstruct", str(bad_files["a"]), str(bad_files["b"]), *args])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert got == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert re.search(pattern, lines[0]), lines[0]
    assert calls == []
    assert [p.name for p in tmp_path.iterdir()] == ["blocker"]


# ------------------------------------------------------------------------------ library
@pytest.fixture(scope="module")
def library_run(cli_pair: Pair) -> tuple[Reconstruction, list[tuple[str, str]]]:
    """``Pipeline().run`` on the 640×480 pair, with the stage events it reported."""
    events: list[tuple[str, str]] = []
    rec = Pipeline().run([cli_pair.a, cli_pair.b], on_stage=lambda s, e: events.append((s, e)))
    return rec, events


def test_library_cameras_at_original_and_working_size_agree(
    library_run: tuple[Reconstruction, list[tuple[str, str]]],
) -> None:
    """``cameras()`` (photo size) equals ``cameras(original_size=False)`` (working size) rescaled."""
    rec, _ = library_run
    orig, work = rec.cameras(), rec.cameras(original_size=False)
    assert [(c.width, c.height) for c in orig] == [CLI_SIZE] * 2
    assert [(c.width, c.height) for c in work] == [SIZE] * 2
    assert orig.world == work.world == "camera_0" and orig.scale == work.scale == "relative"
    for o, w in zip(orig, work):
        r = w.rescaled(*CLI_SIZE)
        assert o.name == w.name
        np.testing.assert_allclose(o.K, r.K, rtol=K_RTOL, atol=0)
        np.testing.assert_array_equal(o.cam_to_world, w.cam_to_world)
        np.testing.assert_allclose(o.rescaled(*SIZE).K, w.K, rtol=2 * K_RTOL, atol=0)  # a rescale and back
    np.testing.assert_allclose(work[0].K, rec.pose.geometry.K0, rtol=K_RTOL, atol=0)
    # cam_to_world holds Rᵀ and −Rᵀt; world_to_cam transposes back (exact) and forms −R(−Rᵀt) = RRᵀt: off t by
    # R's orthogonality defect and two 3-term products (2γ₃), of |t|₁
    np.testing.assert_array_equal(work[1].world_to_cam[:3, :3], rec.pose.geometry.R)
    t = rec.pose.geometry.t
    tol = (3 * _orthogonality(rec.pose.geometry.R) + 2 * 3 * U64) * float(np.abs(t).sum())
    np.testing.assert_allclose(work[1].world_to_cam[:3, 3], t, rtol=0, atol=tol)


def test_library_report_names_every_stage_and_is_json(
    library_run: tuple[Reconstruction, list[tuple[str, str]]],
) -> None:
    """The report names a backend for every stage, times every stage, and is strict JSON."""
    rec, events = library_run
    backends = rec.report.backends
    assert all(isinstance(backends[s], str) and backends[s] for s in STAGES)
    assert all(rec.report.times_s[s] > 0 for s in STAGES)
    json.dumps(rec.report.to_json(), allow_nan=False)
    ends = [s for s, e in events if e == "end"]
    assert [s for s in ends if s in STAGES] == list(STAGES)  # each stage once, in order
    starts = [s for s, e in events if e == "start"]
    assert sorted(starts) == sorted(s for s, e in events if e in ("end", "fail"))  # every start is closed
    assert len(rec.gaussians) == rec.report.gaussians > MIN_GAUSSIANS


def test_library_custom_pose_backend_replaces_the_stage(cli_pair: Pair) -> None:
    """A callable passed as ``pose=`` runs instead of the default and its name is reported."""

    class RecordingPose:
        name = "test:recording-essential"

        def __init__(self) -> None:
            self.inner = EssentialPose(PoseConfig())
            self.calls = 0

        def __call__(self, v0: View, v1: View, matches: Matches, pair: object = None) -> TwoViewGeometry:
            self.calls += 1
            geometry = self.inner(v0, v1, matches, pair)
            geometry.diagnostics["recorded"] = True
            return geometry

    pose = RecordingPose()
    config = ReconstructConfig(views=ViewConfig(size=256))  # small: only the stage wiring is under test
    rec = Pipeline(config, classical_stages(config, pose=pose)).run([cli_pair.a, cli_pair.b])
    assert pose.calls >= 1
    assert rec.report.backends["pose"] == "test:recording-essential"
    assert rec.report.pose["recorded"] is True  # the reported geometry is the custom backend's
    rot_err, _ = _pose_errors(rec, cli_pair)
    assert rot_err < 1.0


def test_library_rejects_unrelated_scenes(bad_files: dict[str, Path]) -> None:
    """With the library's default confidence threshold, two unrelated scenes do not reconstruct."""
    with pytest.raises(ReconstructionError, match="need at least"):
        Pipeline().run([bad_files["a"], bad_files["other_scene"]])


@pytest.mark.parametrize(("n", "message"), [(1, "1 photo given"), (65, "65 photos given: at most 64")])
def test_library_takes_two_to_64_photos(bad_files: dict[str, Path], n: int, message: str) -> None:
    """One photo, or more than the limit, is bad input (InputError), checked once, at the library boundary, before
    anything is read or loaded (the files here do not exist)."""
    with pytest.raises(InputError, match=message):
        reconstruct([bad_files["missing"]] * n)


def test_classical_stages_fill_every_slot_and_the_descriptor_tiers() -> None:
    """The classical factory, as the neural one: every slot, the tiers of ``config.search``; a backend's own
    descriptors get no SIFT wide tier; the pipeline's default is this factory's."""
    config = ReconstructConfig()
    stages = classical_stages(config)
    assert stages.pair is None and stages.scale == "relative" and isinstance(stages.pose, EssentialPose)
    assert stages.fallback is not None and stages.wide is not None and stages.learned is None
    own = classical_stages(config, descriptors=stages.describe)
    assert own.describe is stages.describe and own.wide is None and own.fallback is not None
    assert Pipeline(config).backends() == Pipeline(config, stages).backends()
