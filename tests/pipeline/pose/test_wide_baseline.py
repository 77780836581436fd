"""The second fallback tier (issue 14, wide-baseline recall): the plane tie-break by dense consistency.

A plane's matches alone admit two relative poses; the pose stage refuses them as ambiguous. The tie-break scores
each of the homography's physical decompositions by the keypoints matched along its epipolar lines that it
explains in front of both cameras: only the true pose explains the scene off the plane.
"""

from __future__ import annotations

import numpy as np
import pytest

from macsplat_cli.datasets import synthetic as S
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.descriptors import SiftConfig, SiftDescriptors
from macsplat_cli.pipeline.matching import match_features
from macsplat_cli.pipeline.pose import PoseSearchConfig, dominant_plane, tiebreak
from macsplat_cli.pipeline.pose.tiebreak import plane_tiebreak
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig
from macsplat_cli.pipeline.types import Features, Matches, TwoViewGeometry, View
from macsplat_cli.pipeline.views import ViewConfig, load_views

from support.scenes import PairFactory, PairSpec

W, H = 512, 384


@pytest.fixture(scope="module")
def table_pair(pair_files: PairFactory):  # noqa: ANN201
    """A 30° object orbit (given intrinsics): the views, their SIFT features, the matches that lie on the table
    top (by the ground truth) and the true relative pose."""
    files = pair_files(PairSpec("object", 30.0, (W, H), 60.0, orbit_seed=0), ("view0.png", "view1.png"))
    c0, c1 = files.rendered.cams
    r0 = files.rendered.views[0]
    cfg = ReconstructConfig(views=ViewConfig(intrinsics=files.cameras))
    views = load_views(list(files.photos), cfg.views)
    assert views[0].width == W and views[0].height == H
    feats = [SiftDescriptors(SiftConfig())(v) for v in views]
    m = match_features(feats[0], feats[1])
    # world point of each view-0 match from the true depth: keep the table top (y = 0, normal along y)
    px = np.clip(np.floor(m.xy0).astype(int), 0, [W - 1, H - 1])
    z = r0.depth[px[:, 1], px[:, 0]]
    rays = np.c_[m.xy0, np.ones(len(m))] @ np.linalg.inv(c0.K).T
    X = (np.c_[rays * z[:, None], np.ones(len(m))] @ c0.cam_to_world.T)[:, :3]
    n_y = np.abs(r0.normals[px[:, 1], px[:, 0], 1])
    on_table = (z > 0) & (np.abs(X[:, 1]) < 0.01) & (n_y > 0.9)
    R, t = S.relative_pose(c0, c1)
    return cfg, views, feats, m.subset(on_table), R, t


def _tiebreak(
    pipe: Pipeline, views: list[View], feats: list[Features], matches: Matches
) -> tuple[TwoViewGeometry, list[int]] | None:
    """The plane tie-break with ``pipe``'s pose stage and settings."""
    return plane_tiebreak(views, feats, matches, None, pipe.search.pose, pipe.config.search, pipe.config.pose)


def test_plane_matches_alone_are_ambiguous_and_the_tiebreak_finds_the_true_pose(table_pair) -> None:
    cfg, views, feats, plane, R, _ = table_pair
    assert len(plane) >= 40
    pipe = Pipeline(cfg)
    # the old chain's pose stage on these matches: refused (one plane, two poses) or off; never the answer here
    try:
        g_old = pipe.search.pose(views[0], views[1], plane, None)
        old_ok = rotation_error_deg(g_old.R, R) < 5.0 and not g_old.doubts
    except ReconstructionError:
        old_ok = False
    tied = _tiebreak(pipe, views, feats, plane)
    assert tied is not None
    g, scores = tied
    assert rotation_error_deg(g.R, R) < 2.0
    assert scores[0] >= tiebreak.PLANE_TIEBREAK_MIN
    assert len(scores) == 1 or scores[0] >= cfg.search.plane_tiebreak_margin * scores[1]
    assert not old_ok or len(g.inliers) > len(plane)  # the tie-break adds the scene off the plane


def test_tiebreak_refuses_without_a_clear_winner(table_pair, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg, views, feats, plane, _, _ = table_pair
    tied = _tiebreak(Pipeline(cfg), views, feats, plane)
    assert tied is not None and len(tied[1]) == 2  # the plane's two physical poses were scored
    strict = PoseSearchConfig(plane_tiebreak_margin=1e6)  # no winner by that margin
    assert _tiebreak(Pipeline(ReconstructConfig(views=cfg.views, search=strict)), views, feats, plane) is None
    monkeypatch.setattr(tiebreak, "PLANE_TIEBREAK_MIN", 10**6)  # too little support
    assert _tiebreak(Pipeline(cfg), views, feats, plane) is None


def test_tiebreak_is_not_diluted_by_the_planes_own_matches(table_pair) -> None:
    """Matches on the plane are explained by both of its poses: adding thousands of them (distinctive descriptors,
    exact plane transfer) must leave the scores, the winner and its margin unchanged (a score over all explained
    matches fell to a tie here)."""
    cfg, views, feats, plane, R, _ = table_pair
    pipe = Pipeline(cfg)
    tied = _tiebreak(pipe, views, feats, plane)
    assert tied is not None
    fit = dominant_plane(plane, cfg.pose)  # the tie-break's own estimate of the plane
    assert fit is not None
    Hm = fit[0]
    rng = np.random.default_rng(0)
    n = 3000
    xy0 = plane.xy0[rng.integers(0, len(plane), n)] + rng.uniform(-3.0, 3.0, (n, 2))
    p1 = np.c_[xy0, np.ones(n)] @ Hm.T
    xy1 = p1[:, :2] / p1[:, 2:]
    desc = rng.normal(size=(n, feats[0].desc.shape[1])).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)

    def extend(f: Features, xy: np.ndarray) -> Features:
        return Features(np.r_[f.xy, xy], np.r_[f.desc, desc], np.r_[f.conf, np.ones(n, np.float32)])

    more = [extend(feats[0], xy0), extend(feats[1], xy1)]
    tied_more = _tiebreak(pipe, views, more, plane)
    assert tied_more is not None
    assert rotation_error_deg(tied_more[0].R, R) < 2.0
    s, s_more = tied[1], tied_more[1]
    assert len(s_more) == len(s) and all(abs(a - b) <= 0.02 * a + 5 for a, b in zip(s, s_more)), (s, s_more)


def test_wide_tier_only_runs_when_the_chain_gives_no_pose(table_pair, monkeypatch: pytest.MonkeyPatch) -> None:
    """An easy pair never reaches the second tier (its cost is for hard pairs only)."""
    cfg, views, _, _, _, _ = table_pair
    pipe = Pipeline(ReconstructConfig(views=cfg.views))
    calls = []
    assert pipe.search.wide is not None
    monkeypatch.setattr(pipe.search, "_wide", lambda *a, **k: calls.append(1))

    class Stop(Exception):
        pass

    def stop(*a, **k):
        raise Stop

    pipe.depth = stop  # type: ignore[assignment]
    with pytest.raises(Stop):
        pipe.run([v.path for v in views])
    assert calls == []
