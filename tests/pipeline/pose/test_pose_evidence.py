"""The evidence for a pose that the pose did not choose (issue 25): the a contrario test (NFA), the pose's own
uncertainty and GRIC, on exact synthetic correspondences (no rendering, no SIFT).

The NFA's false-alarm rate is checked where it is defined: on matches drawn from the background model (uniform,
independent), where a pose is "meaningful" by chance at most ``10^max_log10_nfa`` times per pair.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.pipeline.pose import PoseConfig
from macsplat_cli.pipeline.pose.confidence import MAX_LOG10_NFA, MAX_ROTATION_3SIGMA_DEG, accept_pose, weigh_evidence
from macsplat_cli.pipeline.pose.evidence import epipolar_nfa, log10_nfa, pose_evidence
from macsplat_cli.pipeline.types import Matches, TwoViewGeometry, View

W, H, F = 640, 480, 500.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


def _view(source: str = "file") -> View:
    image, mask = np.zeros((H, W, 3), np.float32), np.ones((H, W), bool)
    return View("v", Path("v.png"), image, mask, K.copy(), (W, H), source)  # type: ignore[arg-type]


def _rot(axis_angle_deg: tuple[float, float, float]) -> np.ndarray:
    return cv2.Rodrigues(np.radians(np.asarray(axis_angle_deg, np.float64)).reshape(3, 1))[0]


R_TRUE = _rot((0.0, 20.0, 0.0))
T_TRUE = -R_TRUE @ np.array([2.0, 0.0, 0.5])  # camera 1 = R·X + t


def _matches(
    n: int, *, rng: np.random.Generator, noise: float = 0.3, outliers: float = 0.2, extent: float = 1.0,
    depth: tuple[float, float] = (4.0, 8.0), planar: bool = False,
) -> Matches:  # fmt: skip
    """``n`` matches of random points seen by the two cameras (``extent`` < 1: a cluster near the image centre;
    ``planar``: all on the plane z = 6), a share ``outliers`` of them replaced by uniform random pixels."""
    z = np.full(n, 6.0) if planar else rng.uniform(*depth, n)
    X = np.c_[rng.uniform(-3.0, 3.0, n) * extent * z / 6, rng.uniform(-2.2, 2.2, n) * extent * z / 6, z]
    x0 = X @ K.T
    X1 = X @ R_TRUE.T + T_TRUE
    x1 = X1 @ K.T
    xy0 = x0[:, :2] / x0[:, 2:] + rng.normal(0.0, noise, (n, 2))
    xy1 = x1[:, :2] / x1[:, 2:] + rng.normal(0.0, noise, (n, 2))
    m = int(outliers * n)
    xy1[:m] = rng.uniform((0, 0), (W, H), (m, 2))
    return Matches(xy0, xy1, np.ones(n, np.float32), np.arange(n), np.arange(n))


def _geometry(R: np.ndarray, t: np.ndarray, matches: Matches, *, source: str = "matches") -> TwoViewGeometry:
    return TwoViewGeometry(R, t / np.linalg.norm(t), K.copy(), K.copy(), matches, source=source)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ the NFA itself
def test_log10_nfa_is_the_formula_at_its_minimum() -> None:
    """The minimum over thresholds of log10(N_out (n − s) C(n, k) C(k, s) α^(k − s)), α = c·ε."""
    rng = np.random.default_rng(0)
    r = np.sort(rng.uniform(0.0, 3.0, 40))
    coef, s, n_out = 0.004, 5, 10
    value, k, eps = log10_nfa(r, coef, 1, (s, n_out))

    def direct(kk: int) -> float:
        n = len(r)
        logc = (math.lgamma(n + 1) - math.lgamma(kk + 1) - math.lgamma(n - kk + 1)
                + math.lgamma(kk + 1) - math.lgamma(s + 1) - math.lgamma(kk - s + 1)) / math.log(10)  # fmt: skip
        return math.log10(n_out * (n - s)) + logc + (kk - s) * min(0.0, math.log10(coef * r[kk - 1]))

    values = [direct(kk) for kk in range(s + 1, len(r) + 1)]
    assert k == int(np.argmin(values)) + s + 1 and eps == r[k - 1]
    assert value == pytest.approx(min(values), abs=1e-9 * max(1.0, abs(value)))
    assert log10_nfa(r[:5], coef, 1, (s, n_out)) == (math.inf, 0, pytest.approx(math.nan, nan_ok=True))


def test_random_matches_are_not_meaningful_at_the_stated_rate() -> None:
    """Under the background model (uniform independent matches) a pose is meaningful by chance at most
    ``10^MAX_LOG10_NFA`` times per pair: 2,000 pairs of random matches against random poses give at most the
    2 false alarms that rate allows."""
    rng = np.random.default_rng(1)
    v = _view()
    trials, alarms = 2000, 0
    for _ in range(trials):
        n = int(rng.integers(20, 400))
        m = Matches(rng.uniform((0, 0), (W, H), (n, 2)), rng.uniform((0, 0), (W, H), (n, 2)),
                    np.ones(n, np.float32), np.arange(n), np.arange(n))  # fmt: skip
        R = _rot(tuple(rng.normal(0.0, 20.0, 3)))
        nfa, _, _, _ = epipolar_nfa(v, v, _geometry(R, rng.normal(size=3), m), m.xy0, m.xy1, (False, False))
        alarms += nfa < MAX_LOG10_NFA
    assert alarms <= trials * 10**MAX_LOG10_NFA


# ------------------------------------------------------------------------------ right, wrong, unsupported poses
def test_right_pose_is_supported_and_certain() -> None:
    m = _matches(400, rng=np.random.default_rng(2))
    found, doubts, _ = weigh_evidence(_view(), _view(), _geometry(R_TRUE, T_TRUE, m), m)
    assert doubts == []
    assert found.log10_nfa < -100 and found.inliers >= 0.75 * 320
    assert found.rotation_sigma_deg < 0.2 and found.coverage > 0.4 and not found.planar


def test_pose_twenty_degrees_off_is_not_supported() -> None:
    """The same matches with the rotation 20° off: far fewer explained within a few px (NFA), a large noise."""
    m = _matches(400, rng=np.random.default_rng(3))
    wrong = _rot((0.0, 20.0, 0.0)) @ _rot((5.0, 18.0, 3.0))
    found, doubts, _ = weigh_evidence(_view(), _view(), _geometry(wrong, T_TRUE, m), m)
    assert {d.check for d in doubts} & {"evidence", "uncertainty"}, found


def test_small_cluster_leaves_the_rotation_uncertain() -> None:
    """16 exact-ish matches in a small patch: meaningful against random matches, but the rotation is not pinned
    down (the case of issue 25: 16 matches on 7 % of the photo, a pose 57° off)."""
    m = _matches(16, rng=np.random.default_rng(4), outliers=0.0, extent=0.25)
    found, doubts, _ = weigh_evidence(_view(), _view(), _geometry(R_TRUE, T_TRUE, m), m)
    assert found.log10_nfa < MAX_LOG10_NFA  # the NFA alone would accept it
    assert [d.check for d in doubts] == ["uncertainty"]
    assert "cover" in doubts[0].message and "±" in doubts[0].message
    assert 3 * found.rotation_sigma_deg > MAX_ROTATION_3SIGMA_DEG


def test_unknown_focal_widens_the_uncertainty() -> None:
    """With the focal length a free parameter the rotation's σ is larger than with it known."""
    m = _matches(60, rng=np.random.default_rng(5), outliers=0.0)
    g = _geometry(R_TRUE, T_TRUE, m)
    known = pose_evidence(_view(), _view(), g, m, (False, False))
    free = pose_evidence(_view("prior"), _view("prior"), g, m, (True, True))
    assert free.focal_free and not known.focal_free
    assert free.rotation_sigma_deg > 2 * known.rotation_sigma_deg


def test_gric_recognises_planar_support() -> None:
    rng = np.random.default_rng(6)
    plane = _matches(300, rng=rng, planar=True)
    spread = _matches(300, rng=rng, depth=(3.0, 12.0))
    assert pose_evidence(_view(), _view(), _geometry(R_TRUE, T_TRUE, plane), plane, (False, False)).planar
    found = pose_evidence(_view(), _view(), _geometry(R_TRUE, T_TRUE, spread), spread, (False, False))
    assert not found.planar and found.plane_share < 0.2


def test_point_map_pose_is_not_asked_for_the_matches_uncertainty() -> None:
    """A pose from a point map (PnP) is tested by the NFA of the matches; their uncertainty is reported only."""
    m = _matches(16, rng=np.random.default_rng(4), outliers=0.0, extent=0.25)
    found, doubts, _ = weigh_evidence(
        _view(), _view(), _geometry(R_TRUE, T_TRUE, m, source="pointmap"), m
    )  # fmt: skip
    assert doubts == [] and 3 * found.rotation_sigma_deg > MAX_ROTATION_3SIGMA_DEG


def test_acceptance_weighs_the_putative_matches_not_the_verified_ones() -> None:
    """accept_pose tests the putative matches it is given: a pose whose verified (guided) matches look fine but
    whose putative matches are a small cluster is doubted; the doubt names the figure."""
    rng = np.random.default_rng(7)
    verified = _matches(400, rng=rng, outliers=0.0)
    putative = _matches(16, rng=rng, outliers=0.0, extent=0.25)
    g = _geometry(R_TRUE, T_TRUE, verified)
    conf = accept_pose(_view(), _view(), g, PoseConfig(), False)
    assert conf.ok  # without the checks: the support minimum only
    conf = accept_pose(_view(), _view(), g, PoseConfig(), True, evidence=putative)
    assert [d.check for d in conf.doubts] == ["uncertainty"]
    assert conf.evidence is not None and conf.evidence.putative == 16 and "log10 NFA below -3" in conf.rule
    conf = accept_pose(_view(), _view(), g, PoseConfig(), True, evidence=verified)
    assert conf.ok and conf.checks["log10_nfa"] < -100
