"""The registration's parts on exact synthetic data: tracks from pair matches, the anchored and PnP resections,
the duplicate detection and the pair shortlist's connectivity rule."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from macsplat_cli.pipeline.multiview.pairwise import PairOutcome, _components
from macsplat_cli.pipeline.multiview.resection import anchored_pose, pair_anchor, pnp_pose, reprojection_px
from macsplat_cli.pipeline.multiview.tracks import build_tracks
from macsplat_cli.pipeline.pose.result import PoseResult
from macsplat_cli.pipeline.types import Features, Matches, TwoViewGeometry

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])


def _rot(axis: list[float], deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))[0]


def _features(n: int, seed: int) -> Features:
    rng = np.random.default_rng(seed)
    return Features(rng.uniform(0, 300, (n, 2)), np.ones((n, 8), np.float32), np.ones(n, np.float32))


def _outcome(i: int, j: int, fi: Features, fj: Features, idx_i: list[int], idx_j: list[int]) -> PairOutcome:
    a, b = np.array(idx_i), np.array(idx_j)
    m = Matches(fi.xy[a], fj.xy[b], np.ones(len(a), np.float32), a, b)
    g = TwoViewGeometry(np.eye(3), np.array([1.0, 0, 0]), K, K, m)
    return PairOutcome(i, j, PoseResult(geometry=g, views=[], tier="primary", features=[fi, fj], evidence=m), None, 0)


def test_tracks_chain_matches_and_drop_a_photo_seen_twice() -> None:
    f0, f1, f2 = (_features(10, s) for s in range(3))
    # keypoint 0 of photo 0 ↔ 0 of photo 1 ↔ 0 of photo 2: one track of three; 1↔1 in (0, 1) only: a track of two;
    # photo 2's keypoints 3 and 4 both reach keypoint 2 of photo 0 (through photo 1): photo 2 leaves that track
    outs = [_outcome(0, 1, f0, f1, [0, 1, 2], [0, 1, 2]), _outcome(1, 2, f1, f2, [0, 2], [0, 3]),
            _outcome(0, 2, f0, f2, [2], [4])]  # fmt: skip
    tr = build_tracks(outs)
    assert tr.n_tracks == 3 and tr.conflicts == 2
    by_track = {t: sorted(zip(tr.view[tr.track == t].tolist(), tr.xy[tr.track == t][:, 0].tolist()))
                for t in range(tr.n_tracks)}  # fmt: skip
    sizes = sorted(len(v) for v in by_track.values())
    assert sizes == [2, 2, 3]
    three = next(v for v in by_track.values() if len(v) == 3)
    assert three == [(0, f0.xy[0, 0]), (1, f1.xy[0, 0]), (2, f2.xy[0, 0])]
    with_conflict = next(v for v in by_track.values() if (0, f0.xy[2, 0]) in v)
    assert [v for v, _ in with_conflict] == [0, 1]  # photo 2 left it


def test_connected_components_of_the_accepted_pairs() -> None:
    f = _features(3, 0)
    outs = [_outcome(0, 1, f, f, [0], [0]), _outcome(2, 3, f, f, [0], [0]), PairOutcome(1, 2, None, "no", 0)]
    label = _components(5, outs)
    assert label[0] == label[1] != label[2] == label[3] and label[4] not in label[:4]


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (200, 3))
    R, t = _rot([0.2, 1, 0.1], 12.0), np.array([-0.8, 0.05, 0.1])
    p = (X @ R.T + t) @ K.T
    return X, p[:, :2] / p[:, 2:3], (R, t)


def test_anchored_pose_finds_the_baseline_among_mostly_wrong_correspondences() -> None:
    X, xy, (R, t) = _scene(0)
    rng = np.random.default_rng(1)
    wrong = rng.random(len(X)) < 0.8  # 80 % wrong: PnP's six parameters cannot find the pose, one parameter can
    xy = np.where(wrong[:, None], rng.uniform(0, 320, xy.shape), xy)
    # the registered photo at the identity, the pair's pose: R and the direction of t
    Ra, a, b = pair_anchor(R, t / np.linalg.norm(t), np.eye(3), np.zeros(3), new_is_second=True)
    t_fit, n_in = anchored_pose(X, xy, K, Ra, a, b, 2.0)
    assert np.allclose(t_fit, t, atol=1e-9 * np.linalg.norm(t))
    assert n_in >= (~wrong).sum()


@pytest.mark.parametrize("new_is_second", [True, False])
def test_pair_anchor_composes_the_pair_with_the_registered_pose(new_is_second: bool) -> None:
    R_r, t_r = _rot([1, 0, 0], 20.0), np.array([0.3, -0.2, 1.0])  # the registered photo (world → camera)
    R_k, t_k = _rot([0, 1, 0.3], -15.0), np.array([-1.0, 0.4, 0.2])  # the new photo, to be recovered
    if new_is_second:  # X_k = R_pair X_r + t_pair
        R_pair = R_k @ R_r.T
        t_pair = t_k - R_pair @ t_r
    else:  # X_r = R_pair X_k + t_pair
        R_pair = R_r @ R_k.T
        t_pair = t_r - R_pair @ t_k
    s = np.linalg.norm(t_pair)
    R, a, b = pair_anchor(R_pair, t_pair / s, R_r, t_r, new_is_second)
    assert np.allclose(R, R_k, atol=1e-12) and np.allclose(a + s * b, t_k, atol=1e-12)


def test_pnp_pose_on_exact_correspondences() -> None:
    X, xy, (R, t) = _scene(2)
    found = pnp_pose(X, xy, K, 1.0)
    assert found is not None
    R_fit, t_fit, n_in = found
    assert n_in == len(X) and np.abs(reprojection_px(X, xy, K, R_fit, t_fit)).max() < 1e-6


def test_a_wrong_pair_outside_every_consistent_loop_does_not_start_the_registration() -> None:
    from macsplat_cli.pipeline.multiview.register import _init_pair

    truth = [_rot([0, 1, 0], a) for a in (0.0, 10.0, 20.0, 30.0)]  # world → camera of four photos
    f = _features(3, 0)

    def pair(i: int, j: int, n: int, error_deg: float = 0.0) -> PairOutcome:
        o = _outcome(i, j, f, f, [0] * n, [0] * n)
        o.result.geometry.R = _rot([1, 0, 0], error_deg) @ truth[j] @ truth[i].T
        o.result.geometry.median_parallax_deg = 5.0
        return o

    # (0, 2) is 14° off and has the most matches; (0, 1), (1, 3), (0, 3) close a loop
    outs = [pair(0, 2, 600, 14.0), pair(0, 1, 300), pair(1, 3, 200), pair(0, 3, 150), pair(2, 3, 100, 9.0)]
    first = _init_pair(outs)
    assert (first.i, first.j) == (0, 1)
    # without a consistent loop, the most matches start it
    assert (lambda o: (o.i, o.j))(_init_pair(outs[:1] + outs[4:])) == (0, 2)


def test_free_space_check_drops_a_floater_and_keeps_the_surface() -> None:
    """Two cameras 0.5 apart facing a wall at z = 4: view 0's depth holds the wall and a block at z = 2 that view 1
    sees through (it sees the wall there) → dropped; the wall is confirmed by view 1 → kept; a pixel view 1 cannot
    see (outside its image) is kept: nobody sees through it."""
    from macsplat_cli.pipeline.multiview.depth import free_space_check
    from macsplat_cli.pipeline.types import DepthMap

    h, w = 60, 80
    Kc = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
    Ks, Rs, ts = np.stack([Kc, Kc]), np.stack([np.eye(3), np.eye(3)]), np.array([[0.0, 0, 0], [-0.5, 0, 0]])
    wall = np.full((h, w), 4.0, np.float32)
    d0 = wall.copy()
    d0[25:35, 30:40] = 2.0  # the floater
    maps = [DepthMap(d0, np.ones((h, w), np.float32)), DepthMap(wall, np.ones((h, w), np.float32))]
    out = free_space_check(0, maps, Ks, Rs, ts, [1])
    assert not out.valid[25:35, 30:40].any()
    assert out.valid[:, 20:].sum() == (h * (w - 20) - 100)  # every wall pixel view 1 sees is confirmed
    assert out.valid[:, :5].all()  # the wall's left edge: outside view 1's image (it moved right), kept


def test_triangulation_solves_only_the_tracks_not_kept_yet(monkeypatch: pytest.MonkeyPatch) -> None:
    from types import SimpleNamespace

    from macsplat_cli.pipeline.multiview import register
    from macsplat_cli.pipeline.multiview.tracks import Tracks

    rng = np.random.default_rng(2)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (200, 3))
    poses = [(np.eye(3), np.zeros(3)), (_rot([0, 1, 0], 8.0), np.array([-0.6, 0.0, 0.05])),
             (_rot([0, 1, 0], -8.0), np.array([0.6, 0.02, 0.0]))]  # fmt: skip
    seen_by = {0: range(200), 1: range(150), 2: range(200)}  # tracks 150..199: photos 0 and 2 only
    view, track, xy = [], [], []
    for k, (R, t) in enumerate(poses):
        p = (X[list(seen_by[k])] @ R.T + t) @ K.T
        view += [k] * len(seen_by[k])
        track += list(seen_by[k])
        xy.append(p[:, :2] / p[:, 2:3])
    tracks = Tracks(np.array(view), np.array(track), np.concatenate(xy), 200)
    solved = []
    real = register.triangulate_tracks

    def counting(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        solved.append(args[6])
        return real(*args, **kwargs)

    monkeypatch.setattr(register, "triangulate_tracks", counting)
    st = register._State([SimpleNamespace(K=K)] * 3, tracks)
    st.add(0, *poses[0])
    st.add(1, *poses[1])
    st.triangulate()
    assert solved == [150] and st.point_ok.sum() == 150
    first = st.points.copy()
    st.add(2, *poses[2])
    st.triangulate()
    assert solved == [150, 50]  # the 50 tracks photo 2 completes, not the 150 kept ones again
    assert st.point_ok.all() and np.array_equal(st.points[:150], first[:150])
    assert np.allclose(st.points, X, atol=1e-9)


def test_photo_map_keeps_the_order_and_runs_side_by_side(monkeypatch: pytest.MonkeyPatch) -> None:
    """The depth pairs and the photos' Gaussians go through :func:`photo_map`: the results in the items' order
    whatever finishes first, on more than one thread when the kernels have more, on the caller's alone with one."""
    import threading
    import time

    from macsplat_cli.pipeline.multiview import depth as mv_depth

    def slow_first(k: int) -> tuple[int, str]:
        time.sleep(0.02 if k == 0 else 0.0)
        return k * k, threading.current_thread().name

    monkeypatch.setattr(mv_depth, "kernel_threads", lambda: 2)
    out = mv_depth.photo_map(slow_first, iter(range(6)))
    assert [v for v, _ in out] == [k * k for k in range(6)]
    assert len({name for _, name in out}) == 2
    monkeypatch.setattr(mv_depth, "kernel_threads", lambda: 64)  # many cores: at most SIDE_BY_SIDE_MAX at once
    out = mv_depth.photo_map(slow_first, range(12))
    assert [v for v, _ in out] == [k * k for k in range(12)]
    assert 2 <= len({name for _, name in out}) <= mv_depth.SIDE_BY_SIDE_MAX
    monkeypatch.setattr(mv_depth, "kernel_threads", lambda: 1)
    out = mv_depth.photo_map(slow_first, range(3))
    assert [v for v, _ in out] == [0, 1, 4] and {name for _, name in out} == {threading.current_thread().name}
