"""Planar scenes (issue 14) and unobservable focal lengths (issue 16) in the classical pose stage.

A plane seen from two calibrated views fits two relative poses. The pose stage tells them apart by what the plane
does not share: cheirality (the wrong pose may put part of the plane behind a camera) and matches off the plane,
including those below the confidence gate (``Matches.below_gate``); it refuses only when they are tied. Two views
that look at one point from the same distance cannot fix a shared focal length: the pose stage keeps the prior
and records a doubt instead of presenting a guess as an estimate.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.datasets.synthetic.planar import PlanarMatches, planar_case
from macsplat_cli.errors import PlaneTieError, ReconstructionError
from macsplat_cli.metrics import rotation_error_deg, translation_direction_error_deg
from macsplat_cli.pipeline.pose import PoseConfig, PoseDiagnostics, PoseSearch, PoseSearchConfig, estimate_pose
from macsplat_cli.pipeline.pose.planar import ambiguous
from macsplat_cli.pipeline.types import IntrinsicsSource, Matches, TwoViewGeometry, View
from macsplat_cli.pipeline.views import prior_focal

W, H = 320, 240
K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])


def _view(K_: np.ndarray = K, source: IntrinsicsSource = "file", width: int = W, height: int = H) -> View:
    image = np.zeros((height, width, 3), np.float32)
    return View("v", Path("v.png"), image, np.ones((height, width), bool), K_.copy(), (width, height), source)


def _matches(xy0: np.ndarray, xy1: np.ndarray) -> Matches:
    n = len(xy0)
    return Matches(xy0, xy1, np.ones(n, np.float32), np.arange(n), np.arange(n))


def _planar_matches(p: PlanarMatches) -> Matches:
    m = _matches(p.xy0, p.xy1)
    m.below_gate = _matches(p.below_gate.xy0, p.below_gate.xy1) if p.below_gate is not None else None
    return m


def _project(X: np.ndarray, R: np.ndarray, t: np.ndarray, K_: np.ndarray = K, size=(W, H)):
    X1 = X @ R.T + t
    p0, p1 = X @ K_.T, X1 @ K_.T
    xy0, xy1 = p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]
    ok = (X[:, 2] > 0.1) & (X1[:, 2] > 0.1) & np.all((xy0 >= 0) & (xy0 < size) & (xy1 >= 0) & (xy1 < size), axis=1)
    return xy0, xy1, ok


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _right(g, R: np.ndarray, t: np.ndarray) -> bool:
    return rotation_error_deg(g.R, R) < 2 and translation_direction_error_deg(g.t, t) < 10


def _random_plane_case(seed: int, off: float | None) -> tuple[Matches, np.ndarray, np.ndarray]:
    """benchmarks/pose_stress.py's ``random`` motion (rotation 0–20°, translation 0.5 over a plane 6 units away):
    200 plane matches (``off`` None), or a table-top with ``off`` of the points on objects, half of those below
    the confidence gate, plus outliers."""
    p, R, t = planar_case(seed, off, "random")
    return _planar_matches(p), R, t


def _table_pure_plane(seed: int) -> tuple[Matches, np.ndarray, np.ndarray]:
    """200 matches on a table seen from 6 units away, 45° above it, the second photo 25° further round."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 360)

    def eye(a_deg: float) -> np.ndarray:
        a, e = math.radians(a_deg), math.radians(45.0)
        return 6.0 * np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])

    C0, C1 = eye(az), eye(az + 25.0)
    Rc0, Rc1 = _look_at(C0, np.zeros(3)), _look_at(C1, np.array([0.2, 0.0, -0.1]))
    R, t = Rc1 @ Rc0.T, Rc1 @ (C0 - C1)
    table = np.c_[rng.uniform(-3, 3, 1200), np.zeros(1200), rng.uniform(-2, 2, 1200)]
    xy0, xy1, ok = _project((table - C0) @ Rc0.T, R, t)
    xy0, xy1 = xy0[ok][:200], xy1[ok][:200]
    return _matches(xy0 + rng.normal(0, 0.3, xy0.shape), xy1 + rng.normal(0, 0.3, xy1.shape)), R, t


def _pose(m: Matches, config: PoseConfig | None = None, seed: int = 0, v: View | None = None):
    cv2.setRNGSeed(seed)
    return estimate_pose(v or _view(), v or _view(), m, config)


# ------------------------------------------------------------------------------------------------ planar scenes
def test_a_pure_plane_resolved_by_cheirality() -> None:
    """A table seen obliquely: the plane's other pose puts part of it behind a camera, so it is resolved where
    the check before issue 14 refused it as ambiguous."""
    m, R, t = _table_pure_plane(0)
    g = _pose(m)
    assert _right(g, R, t)
    assert g.diagnostics["planar_candidates"] >= 2 and len(g.inliers) >= 195


def test_a_tied_pure_plane_is_refused() -> None:
    """Frontal plane, small motion: both poses put every point in front of both cameras (checked on the true
    points), nothing else tells them apart: refused, not guessed."""
    m, R, t = _random_plane_case(0, None)
    with pytest.raises(ReconstructionError, match="ambiguous.*no other matches tell them apart"):
        _pose(m)


@pytest.mark.parametrize("seed, off", [(8, 0.05), (23, 0.05), (9, 0.1)])
def test_matches_below_the_gate_resolve_the_plane(seed: int, off: float) -> None:
    """A table-top with a few matches on objects, half of them below the confidence gate: without those the
    plane's two poses tie (refused), with them the right one wins."""
    m, R, t = _random_plane_case(seed, off)
    assert m.below_gate is not None
    with pytest.raises(ReconstructionError, match="ambiguous"):
        _pose(_matches(m.xy0, m.xy1), None, seed)
    g = _pose(m, None, seed)
    assert _right(g, R, t)
    diag = g.diagnostics
    assert diag["planar_evidence"] >= 8 and diag["planar_matches_scored"] == len(m) + len(m.below_gate)
    assert g.inliers.counts.get("verified") == len(g.inliers) <= len(m)  # the sub-gate matches stay out


def test_random_planes_are_never_wrong() -> None:
    """Over 20 planar cases with and without objects, every accepted pose is right."""
    accepted = 0
    for seed in range(20):
        for off in (None, 0.05):
            m, R, t = _random_plane_case(seed, off)
            try:
                g = _pose(m, None, seed)
            except ReconstructionError:
                continue
            accepted += 1
            assert _right(g, R, t), f"seed {seed}, off {off}"
    assert accepted >= 15


def _tied_then(case: tuple[Matches, np.ndarray, np.ndarray]) -> PoseSearch:
    """A search whose primary tier's pose stage finds a plane's two poses tied, and whose fallback tier's pose stage
    gives ``case``'s true pose on ``case``'s matches (stub descriptors, matcher and pose: no images)."""
    m, R, t = case

    def describe(views: list[View], pair: object = None) -> list[str]:
        return [describe.name] * 2  # type: ignore[attr-defined]

    def fallback(views: list[View], pair: object = None) -> list[str]:
        return ["fallback"] * 2

    def pose(v0: View, v1: View, matches: Matches, pair: object = None) -> TwoViewGeometry:
        if matches is not m:
            raise ambiguous(161, 143, (14, 6))
        return TwoViewGeometry(R, t / np.linalg.norm(t), K.copy(), K.copy(), m, median_parallax_deg=5.0)

    describe.name, fallback.name = "primary", "fallback"  # type: ignore[attr-defined]
    cfg = PoseSearchConfig(confidence=False, guided_band_px=None)
    return PoseSearch(cfg, PoseConfig(), describe=describe, match=lambda f0, f1: m if f0 == "fallback" else
                      _matches(np.zeros((20, 2)), np.ones((20, 2))), pose=pose, fallback=fallback)  # type: ignore[arg-type]  # fmt: skip


def test_a_plane_tied_in_one_tier_must_be_settled_by_the_next() -> None:
    """ICL (0, 2) (benchmarks/history/pose.md, 2026-11-29): the primary tier found a plane's two poses tied; the
    fallback tier's pose, one of the same plane's two poses whose matches do not tell them apart (fewer of them on
    the plane than the pose stage's own contest asks), is refused with the tie; a fallback pose whose matches off
    the plane (above and below the gate) win that contest stands."""
    with pytest.raises(PlaneTieError, match="pose is ambiguous: the 161 verified matches lie on one plane"):
        _tied_then(_random_plane_case(0, None))([_view(), _view()])
    result = _tied_then(_random_plane_case(8, 0.05))([_view(), _view()])
    assert result.tier == "fallback"


def test_a_tie_is_the_reason_given_when_no_later_tier_gives_a_pose() -> None:
    """The primary tier found a plane's two poses tied and the fallback tier found no pose at all: the refusal
    names the tie (what the photos show), not the fallback's own failure."""
    m, _, _ = _random_plane_case(0, None)
    search = _tied_then((m, np.eye(3), np.array([1.0, 0.0, 0.0])))
    tie_then_nothing = search.pose

    def pose(v0: View, v1: View, matches: Matches, pair: object = None) -> TwoViewGeometry:
        if matches is m:
            raise ReconstructionError("only 9 matches were verified (15 needed)")
        return tie_then_nothing(v0, v1, matches, pair)

    search.pose = pose  # type: ignore[method-assign]
    with pytest.raises(PlaneTieError, match="pose is ambiguous"):
        search([_view(), _view()])


# ------------------------------------------------------------------------------------------------ focal length
def _orbit_case(angle_deg: float, fov_deg: float, seed: int = 0) -> tuple[Matches, np.ndarray, np.ndarray, float]:
    """Two cameras 5 units from an object (points within 1 unit of the target), both aimed at it, ``angle_deg``
    apart around it: the configuration whose shared focal two views cannot fix. 512×384, 0.3 px noise."""
    rng = np.random.default_rng(seed)
    f = 256.0 / math.tan(math.radians(fov_deg) / 2)
    Kt = np.array([[f, 0, 256.0], [0, f, 192.0], [0, 0, 1]])
    a = math.radians(angle_deg)
    C0 = np.array([0.0, -1.5, -5.0])
    C1 = np.array([5.0 * math.sin(a), -1.5, -5.0 * math.cos(a)])
    Rc0, Rc1 = _look_at(C0, np.zeros(3)), _look_at(C1, np.zeros(3))
    R, t = Rc1 @ Rc0.T, Rc1 @ (C0 - C1)
    P = rng.uniform(-1, 1, (3000, 3))
    xy0, xy1, ok = _project((P - C0) @ Rc0.T, R, t, Kt, (512, 384))
    xy0, xy1 = xy0[ok][:600], xy1[ok][:600]
    m = _matches(xy0 + rng.normal(0, 0.3, xy0.shape), xy1 + rng.normal(0, 0.3, xy1.shape))
    return m, R, t, f


def _prior_view() -> View:
    f = prior_focal(512, 384, 60.0)
    return _view(np.array([[f, 0, 256.0], [0, f, 192.0], [0, 0, 1]]), "prior", 512, 384)


def test_an_object_orbit_keeps_the_prior_focal_with_a_doubt() -> None:
    """Both cameras aimed at the object from the same distance, 45° apart, true field of view 40°: the focal is
    not observable; the prior is kept (not reported as estimated) and a doubt names the remedy."""
    m, R, t, f_true = _orbit_case(45.0, 40.0)
    v = _prior_view()
    g = _pose(m, v=v)
    assert g.diagnostics["focal_observable"] is False and g.focal_estimated is False
    np.testing.assert_allclose(g.K0, v.K)
    doubts = g.doubts
    assert isinstance(doubts, list) and len(doubts) == 1
    assert "focal length cannot be determined" in doubts[0] and "--focal" in doubts[0]
    assert "look at the same point" in doubts[0]
    assert g.diagnostics["focal_axes_gap"] < 0.1


def test_the_pose_diagnostics_are_one_typed_record_in_the_order_of_the_steps() -> None:
    """The classical pose fills one :class:`PoseDiagnostics` (no free-form dict through its helpers); the report's
    ``pose`` keys are the measured fields, in the order the steps measure them: the focal, the RANSAC, the plane,
    the final inliers, the plausibility checks. A planar pair with the prior's focal runs every step."""
    m, _, _ = _table_pure_plane(0)
    g = _pose(m, v=_prior_view())
    names = [f.name for f in dataclasses.fields(PoseDiagnostics)]
    keys = list(g.diagnostics)
    assert keys == [n for n in names if n in keys]
    for step in ("ransac_inliers", "focal_data_std", "focal_observable", "planar_candidates", "inliers",
                 "flipped_triangles", "homography_inliers"):  # fmt: skip
        assert step in keys
    assert PoseDiagnostics(inliers=3, planar_resolved="essential").as_dict() == {
        "planar_resolved": "essential",
        "inliers": 3,
    }


def test_a_general_pair_self_calibrates_without_a_doubt() -> None:
    """Sideways-and-forward motion with rotation, scene 4–10 units deep: the focal is estimated, no doubt."""
    rng = np.random.default_rng(1)
    f_true = 256.0 / math.tan(math.radians(25))
    Kt = np.array([[f_true, 0, 256.0], [0, f_true, 192.0], [0, 0, 1]])
    R = cv2.Rodrigues(np.array([0.05, 0.2, 0.03]))[0]
    t = np.array([-0.8, 0.1, 0.3])
    X = np.c_[rng.uniform(-3, 3, (4000, 2)), rng.uniform(4, 10, 4000)]
    xy0, xy1, ok = _project(X, R, t, Kt, (512, 384))
    xy0, xy1 = xy0[ok][:500], xy1[ok][:500]
    m = _matches(xy0 + rng.normal(0, 0.3, xy0.shape), xy1 + rng.normal(0, 0.3, xy1.shape))
    g = _pose(m, v=_prior_view())
    assert g.diagnostics["focal_observable"] is True and g.focal_estimated is True
    assert g.doubts == []
    assert abs(g.K0[0, 0] / f_true - 1) < 0.03
    assert rotation_error_deg(g.R, R) < 0.5
