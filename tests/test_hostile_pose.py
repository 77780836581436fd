"""Hostile input to the pose stage (issue 23, the second round of hostile input).

* A pair at ``--size 128`` crashed the pose stage with OpenCV's ``!model.empty()`` assertion (exit 1, "internal
  error"). Not the CMYK JPEG of the report (OpenCV decodes CMYK and YCCK JPEGs to the right colours:
  ``tests/test_images.py``); the cause is repeated correspondences (one keypoint with several SIFT orientations
  matched more than once: 441 matches, 396 distinct), which make USAC's minimal samples degenerate. Every OpenCV
  geometry call of the pose stage now runs within its preconditions; degenerate matches are a
  :class:`ReconstructionError`, never a ``cv2.error``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_neural_pipeline import _run

from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import NonFiniteError, ReconstructionError
from macsplat_cli.pipeline.neural import pose_from_pointmap
from macsplat_cli.pipeline.pose import _robust_fit, estimate_pose, find_homography
from macsplat_cli.pipeline.types import Matches, View


# ------------------------------------------------------------------------------ fixtures and helpers
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
    H2, m2 = _robust_fit(always_asserts_on_repeats, rep0, rep1, 4, "test")
    assert H2 is not None and m2 is not None and m2.shape == (70,)
    np.testing.assert_array_equal(m2[60:], m2[:10])  # each repeat flagged as its first occurrence

    def always_asserts(xa: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise cv2.error("(-215:Assertion failed) !model.empty()")

    assert _robust_fit(always_asserts, rep0, rep1, 4, "test") == (None, None)


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

    scene = syn.make_scene("room", 0, textured=True)
    cams = syn.orbit_pair("room", 5, width=256, height=192)
    paths = []
    for k, cam in enumerate(cams):
        rgb = np.rint(np.clip(syn.render(scene, cam).image, 0, 1) * 255).astype(np.uint8)
        paths.append(tmp_path / f"view{k}.jpg")
        Image.fromarray(rgb).convert("CMYK").save(paths[-1], "JPEG")
    code, _, err = _run(["reconstruct", *paths, "-o", tmp_path / "s.ply", "--size", "128", "-q",
                         "--report", tmp_path / "r.json"])  # fmt: skip
    assert code == 0, err
    assert json.loads((tmp_path / "r.json").read_text())["pose"]["doubts"] == []
