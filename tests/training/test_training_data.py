"""Training data: candidate pairs by coverage / angle, deterministic samples and loaders, crops, bad images."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import macsplat_cli.datasets.synthetic as S
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import EvalDataset, load_dataset
from macsplat_cli.datasets.coverage import coverage_matrix
from macsplat_cli.errors import DatasetError, InputError
from macsplat_cli.images import save_image
from macsplat_cli.training.data import (
    CandidatePairs,
    PairDataset,
    PairSamplingConfig,
    TrainPair,
    candidate_pairs,
    make_loader,
    resize_and_crop,
)

W, H, Z = 96, 64, 3.0
K = S.intrinsics(W, H, 60.0)
PLANE_X = (0.0, 0.35, 1.0, 1.9, 3.0)
"""Camera x positions in front of a plane: pairwise coverage 1 − |Δx|·fx/(Z·W) ≥ 0.03 from 0.3, 0.5 and 0.85."""
SMALL = (48, 32)


def camera(
    name: str, x: float = 0.0, yaw_deg: float = 0.0, size: tuple[int, int] = (W, H), k: np.ndarray = K
) -> Camera:
    T = np.eye(4)
    T[:3, :3] = S.rotation_about((0, 1, 0), yaw_deg)
    T[0, 3] = x
    return Camera(name, size[0], size[1], k, T)


def plane_coverage(xa: float, xb: float) -> float:
    return 1.0 - abs(xb - xa) * K[0, 0] / Z / W


def write_plane(root: Path, depth: bool = True, cams: list[Camera] | None = None) -> Path:
    scene = S.Scene([S.Quad((-6.0, -4.0, Z), (12.0, 0.0, 0.0), (0.0, 8.0, 0.0))], lighting=None)
    cams = cams if cams is not None else [camera(f"f{i}", x) for i, x in enumerate(PLANE_X)]
    S.write_dataset(root, scene, cams, depth=depth, supersample=1)
    return root


@pytest.fixture(scope="module")
def plane(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_plane(tmp_path_factory.mktemp("train") / "plane")


@pytest.fixture(scope="module")
def plane_ds(plane: Path) -> EvalDataset:
    return load_dataset(plane)


@pytest.fixture(scope="module")
def plane_pairs(plane_ds: EvalDataset) -> list[TrainPair]:
    return candidate_pairs(plane_ds, PairSamplingConfig(size=SMALL))


def batches(loader) -> list[dict[str, torch.Tensor]]:  # noqa: ANN001
    return list(loader)


def same(a: list[dict[str, torch.Tensor]], b: list[dict[str, torch.Tensor]]) -> bool:
    return len(a) == len(b) and all(
        x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x) for x, y in zip(a, b)
    )


# ------------------------------------------------------------------------------------ candidate pairs
def test_pairs_by_coverage_respect_the_range_and_targets_are_covered(plane_ds: EvalDataset) -> None:
    cfg = PairSamplingConfig(coverage=(0.5, 0.85), size=SMALL)
    pairs = candidate_pairs(plane_ds, cfg)
    cov = coverage_matrix(plane_ds.scenes[0])
    n = len(PLANE_X)
    expected = {
        (a, b) for a in range(n) for b in range(n) if a != b and 0.5 <= plane_coverage(PLANE_X[a], PLANE_X[b]) <= 0.85
    }
    assert {p.context for p in pairs} == expected
    assert len(expected) == 10  # both orders of 5 pairs; 0.899 (too close) and 0.452 (too wide) excluded
    for p in pairs:
        a, b = p.context
        assert p.scene == 0 and 0.5 <= cov[a, b] <= 0.85
        assert p.targets and a not in p.targets and b not in p.targets
        assert all(max(cov[a, t], cov[b, t]) >= 0.5 for t in p.targets)
        others = set(range(n)) - {a, b} - set(p.targets)
        assert all(max(cov[a, f], cov[b, f]) < 0.5 for f in others)  # every covered frame is a candidate
    assert candidate_pairs(plane_ds, cfg) == pairs  # deterministic


def test_pairs_by_angle_without_depth(tmp_path: Path) -> None:
    yaws = (0.0, 2.0, 10.0, 30.0, 50.0, 80.0)
    cams = [camera(f"f{i}", 0.1 * i, y) for i, y in enumerate(yaws)]
    root = write_plane(tmp_path / "nodepth", depth=False, cams=cams)
    ds = load_dataset(root)
    assert not ds.scenes[0].has_depth
    pairs = candidate_pairs(ds, PairSamplingConfig(min_angle_deg=5.0, max_angle_deg=60.0, size=SMALL))
    n = len(yaws)
    expected = {(a, b) for a in range(n) for b in range(n) if 5.0 <= abs(yaws[a] - yaws[b]) <= 60.0}
    assert {p.context for p in pairs} == expected
    for p in pairs:
        a, b = p.context
        want = tuple(
            f for f in range(n) if f not in (a, b) and max(abs(yaws[f] - yaws[a]), abs(yaws[f] - yaws[b])) <= 60
        )
        assert p.targets == want and want
    # no pair: every optical axis within 5° of the others
    with pytest.raises(DatasetError, match="no valid pair") as e:
        candidate_pairs(ds, PairSamplingConfig(min_angle_deg=85.0, max_angle_deg=90.0, size=SMALL))
    assert str(root) in str(e.value)


def test_no_valid_pair_by_coverage_is_a_dataset_error(plane_ds: EvalDataset) -> None:
    with pytest.raises(DatasetError, match="no valid pair") as e:
        candidate_pairs(plane_ds, PairSamplingConfig(coverage=(0.95, 1.0), size=SMALL))
    assert str(plane_ds.root) in str(e.value)
    with pytest.raises(DatasetError, match=r"\[3, 3\]"):  # a given coverage matrix of the wrong shape
        candidate_pairs(plane_ds, PairSamplingConfig(size=SMALL), coverage={"plane": np.eye(3)})


def test_given_coverage_matrix_is_used(plane_ds: EvalDataset) -> None:
    n = len(PLANE_X)
    cov = np.zeros((n, n))
    cov[0, 3] = cov[3, 4] = 0.9
    name = plane_ds.scenes[0].name
    pairs = candidate_pairs(plane_ds, PairSamplingConfig(size=SMALL), coverage={name: cov})
    assert pairs == [TrainPair(0, (0, 3), (4,))]  # (3, 4) has no target: f must be seen by 3 or 4


def test_config_is_validated() -> None:
    for bad in (
        {"size": (250, 192)},
        {"coverage": (0.6, 0.5)},
        {"targets": 0},
        {"min_angle_deg": 70.0},
        {"samples_per_epoch": 0},
        {"crop": "center"},
    ):
        with pytest.raises(InputError):
            PairSamplingConfig(**bad)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ samples and loaders
def test_sample_shapes_and_values(plane_ds: EvalDataset, plane_pairs: list[TrainPair]) -> None:
    cfg = PairSamplingConfig(size=SMALL, targets=3)
    ds = PairDataset(plane_ds, plane_pairs, cfg, depth=True)
    assert len(ds) == len(plane_pairs) == 16
    s = ds[5]
    w, h = SMALL
    assert s["context"].shape == (2, 3, h, w) and s["context"].dtype == torch.float32
    assert s["target"].shape == (3, 3, h, w)
    assert 0.0 <= float(s["context"].min()) and float(s["context"].max()) <= 1.0 and float(s["context"].std()) > 0.01
    assert s["context_K"].shape == (2, 3, 3) and s["context_K"].dtype == torch.float64
    assert s["target_K"].shape == (3, 3, 3) and s["target_c2w"].shape == (3, 4, 4)
    assert s["index"].dtype == torch.int64 and int(s["index"]) == 5
    frames = plane_ds.scenes[0].frames
    a, b = plane_pairs[5].context
    assert torch.equal(s["context_c2w"][0], torch.from_numpy(frames[a].camera.cam_to_world.copy()))
    assert torch.equal(s["context_c2w"][1], torch.from_numpy(frames[b].camera.cam_to_world.copy()))
    np.testing.assert_allclose(s["context_K"][0].numpy(), frames[a].camera.rescaled(w, h).K, atol=1e-12)
    assert s["context_depth"].shape == (2, h, w) and torch.allclose(s["context_depth"], torch.tensor(Z), atol=2e-3)
    centres = {tuple(np.round(f.camera.center, 6)) for f in frames}
    for T in s["target_c2w"]:
        assert tuple(np.round(T[:3, 3].numpy(), 6)) in centres
    # targets: distinct candidates of the pair (the pair has at least 3)
    assert len(plane_pairs[5].targets) >= 3
    t_idx = [
        next(j for j, f in enumerate(frames) if np.allclose(f.camera.cam_to_world, T.numpy())) for T in s["target_c2w"]
    ]
    assert len(set(t_idx)) == 3 and set(t_idx) <= set(plane_pairs[5].targets)


def test_same_seed_same_batches_other_seed_or_epoch_differs(
    plane_ds: EvalDataset, plane_pairs: list[TrainPair]
) -> None:
    cfg = PairSamplingConfig(size=SMALL, targets=2)

    def run(seed: int, epoch: int = 0, workers: int = 0) -> list[dict[str, torch.Tensor]]:
        ds = PairDataset(plane_ds, plane_pairs, cfg, seed=seed)
        loader = make_loader(ds, batch_size=4, workers=workers, seed=seed)
        loader.set_epoch(epoch)
        return batches(loader)

    first = run(0)
    assert len(first) == 4 and first[0]["context"].shape == (4, 2, 3, SMALL[1], SMALL[0])
    assert same(first, run(0))
    assert not same(first, run(1))
    other_epoch = run(0, epoch=1)
    assert not same(first, other_epoch)
    assert same(other_epoch, run(0, epoch=1))
    order = torch.cat([b["index"] for b in first])
    assert sorted(order.tolist()) == list(range(16)) and order.tolist() != list(range(16))  # every pair, shuffled
    assert same(first, run(0, workers=2))  # workers do not change anything


def test_set_epoch_changes_the_target_draw(plane_ds: EvalDataset, plane_pairs: list[TrainPair]) -> None:
    ds = PairDataset(plane_ds, plane_pairs, PairSamplingConfig(size=SMALL, targets=2), seed=3)
    e0 = [ds[i]["target_c2w"] for i in range(len(ds))]
    ds.set_epoch(1)
    e1 = [ds[i]["target_c2w"] for i in range(len(ds))]
    assert any(not torch.equal(x, y) for x, y in zip(e0, e1))
    ds.set_epoch(0)
    assert all(torch.equal(x, ds[i]["target_c2w"]) for i, x in enumerate(e0))


def test_samples_per_epoch_draws_a_permutation_of_pairs(plane_ds: EvalDataset, plane_pairs: list[TrainPair]) -> None:
    ds = PairDataset(plane_ds, plane_pairs, PairSamplingConfig(size=SMALL, samples_per_epoch=32), seed=0)
    assert len(ds) == 32
    ks = [ds._pair_index(i) for i in range(32)]
    assert sorted(ks[:16]) == list(range(16)) and sorted(ks[16:]) == list(range(16)) and ks[:16] != ks[16:]
    ds.set_epoch(1)
    assert [ds._pair_index(i) for i in range(32)] != ks


def test_per_scene_draws_a_scene_then_a_first_context_then_a_partner(plane_ds: EvalDataset) -> None:
    """The release's sampling: scenes equally often whatever their pair counts, then first contexts equally often,
    then partners; ``per_scene × scenes`` samples an epoch, each a function of (seed, epoch, i)."""
    listed = [(0, (0, 2)), (1, (0, 1)), (0, (1, 0)), (0, (0, 1)), (0, (0, 3))]  # unsorted on purpose
    pairs = CandidatePairs.from_pairs([TrainPair(sc, ctx, (4,)) for sc, ctx in listed])
    rng = np.random.default_rng(0)
    n = 24_000
    counts = np.bincount([pairs.draw_by_scene(rng) for _ in range(n)], minlength=len(listed)) / n
    want = np.array([1 / 12, 1 / 2, 1 / 4, 1 / 12, 1 / 12])  # scene ½ × first context ½ × partner ⅓ (or 1)
    assert np.all(np.abs(counts - want) < 5 * np.sqrt(want * (1 - want) / n)), counts  # 5 binomial s.d.
    assert pairs.num_scenes == 2
    one_scene = candidate_pairs(plane_ds, PairSamplingConfig(size=SMALL))
    ds = PairDataset(plane_ds, one_scene, PairSamplingConfig(size=SMALL, per_scene=12), seed=3)
    assert len(ds) == 12
    ks = [ds._pair_index(i) for i in range(12)]
    assert ks == [ds._pair_index(i) for i in range(12)] and len(set(ks)) > 3
    ds.set_epoch(1)
    assert [ds._pair_index(i) for i in range(12)] != ks
    with pytest.raises(InputError, match="give one"):
        PairSamplingConfig(per_scene=20, samples_per_epoch=10)


def test_distributed_ranks_split_the_samples(plane_ds: EvalDataset, plane_pairs: list[TrainPair]) -> None:
    cfg = PairSamplingConfig(size=SMALL, targets=1)
    ds = PairDataset(plane_ds, plane_pairs, cfg, seed=7)

    def got(rank: int, world: int) -> dict[int, dict[str, torch.Tensor]]:
        loader = make_loader(ds, batch_size=3, seed=7, rank=rank, world_size=world, drop_last=False)
        loader.set_epoch(2)
        out = {}
        for b in loader:
            for j, i in enumerate(b["index"].tolist()):
                assert i not in out
                out[i] = {k: v[j] for k, v in b.items()}
        return out

    one, r0, r1 = got(0, 1), got(0, 2), got(1, 2)
    assert len(r0) == len(r1) == 8 and not set(r0) & set(r1)
    assert set(r0) | set(r1) == set(one) == set(range(16))
    for i, s in {**r0, **r1}.items():  # the same sample whatever the rank
        assert all(torch.equal(s[k], one[i][k]) for k in s)


def test_a_resumed_epoch_skips_the_done_batches_without_loading_them(
    plane_ds: EvalDataset, plane_pairs: list[TrainPair]
) -> None:
    cfg = PairSamplingConfig(size=SMALL, targets=1)
    ds = PairDataset(plane_ds, plane_pairs, cfg, seed=4, epoch=1)
    whole = batches(make_loader(ds, batch_size=3, seed=4))
    loaded: list[int] = []
    real = ds.sample
    ds.sample = lambda i: (loaded.append(i), real(i))[1]  # type: ignore[method-assign]
    rest = batches(make_loader(ds, batch_size=3, seed=4, start_batch=2))
    assert same(rest, whole[2:]) and len(rest) == 3
    assert sorted(loaded) == sorted(torch.cat([b["index"] for b in whole[2:]]).tolist())  # nothing else was read


def _brute_force_pairs(seen: np.ndarray, pair_ok: np.ndarray, both: bool) -> list[tuple[int, int, tuple[int, ...]]]:
    """What candidate_pairs listed before: every pair with its targets (O(N³))."""
    out = []
    for a, b in zip(*np.nonzero(pair_ok)):
        ok = (seen[a] & seen[b]) if both else (seen[a] | seen[b])
        ok[[a, b]] = False
        if ok.any():
            out.append((int(a), int(b), tuple(int(f) for f in np.flatnonzero(ok))))
    return out


def test_compact_pairs_give_the_targets_of_the_listing_they_replace() -> None:
    """Random visibility: the pairs kept, their targets (in order), and the frames a subset names, as listed in full."""
    from macsplat_cli.training.pairs import CandidatePairs, _TargetRule

    rng = np.random.default_rng(0)
    for trial in range(120):
        n = int(rng.integers(2, 12))
        seen = rng.random((n, n)) < rng.random()
        if trial % 2:
            seen |= seen.T
        np.fill_diagonal(seen, trial % 3 != 0)
        pair_ok = (rng.random((n, n)) < rng.random()) & ~np.eye(n, dtype=bool)
        for both in (False, True):
            rule = _TargetRule(seen, both)
            a, b = np.nonzero(rule.has_targets(pair_ok))
            pairs = CandidatePairs(np.zeros(len(a)), np.stack([a, b], 1), {0: rule})
            want = _brute_force_pairs(seen, pair_ok, both)
            assert pairs == [TrainPair(0, (x, y), t) for x, y, t in want]
            if not want:
                continue
            keep = np.flatnonzero(rng.random(len(want)) < 0.5)[::-1]
            sub = pairs.subset(keep)
            assert list(sub) == [pairs[int(k)] for k in keep]
            assert set(sub.used_frames().get(0, [])) == {f for k in keep for f in (*want[k][:2], *want[k][2])}
            explicit = CandidatePairs.from_pairs(list(pairs))
            assert explicit == pairs and explicit.subset(keep) == sub


# ------------------------------------------------------------------------------------ resize / crop
def _blob_image(cam: Camera, X: np.ndarray, sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """An image with a Gaussian blob centred on the projection of ``X``; returns (image, (u, v))."""
    Xc = cam.world_to_cam @ np.append(X, 1.0)
    uv = (cam.K @ Xc[:3])[:2] / Xc[2]
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
    g = np.exp(-((xs - uv[0]) ** 2 + (ys - uv[1]) ** 2) / (2 * sigma**2)).astype(np.float32)
    return np.repeat(g[..., None], 3, axis=2), uv


def _centroid(img: np.ndarray) -> np.ndarray:
    h, w = img.shape
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    wgt = np.clip(img - 0.05, 0.0, None)
    return np.array([(wgt * xs).sum(), (wgt * ys).sum()]) / wgt.sum()


def test_resize_and_crop_keep_K_consistent(tmp_path: Path) -> None:
    """A 3-D point lands on the same image content before and after resize/crop."""
    k = np.array([[120.0, 0.0, 70.3], [0.0, 118.0, 55.1], [0.0, 0.0, 1.0]])
    X = np.array([0.15, -0.1, 2.5])
    cams = [camera(f"v{i}", x, yaw, size=(160, 100), k=k) for i, (x, yaw) in enumerate([(0, 0), (0.3, -4), (-0.2, 3)])]
    root = tmp_path / "blobs"
    (root / "images").mkdir(parents=True)
    for cam in cams:
        img, uv = _blob_image(cam, X)
        assert abs(_centroid(img[..., 0]) - uv).max() < 0.02  # the centroid measures the projection
        save_image(root / "images" / f"{cam.name}.png", img)
    save_cameras(root / "cameras.json", CameraSet(cams, world="world"))
    data = load_dataset(root)
    # crop x (77x48 → 64), crop y (64x40 → 48), no resize in x; then the release's principal-point window first
    # (x 0..140, y 11..99 around (70.3, 55.1)): the point still lands on its blob, and the principal point sits
    # within half a window pixel (scaled) of the image's centre
    for size, crop in (((64, 48), "centre"), ((48, 64), "centre"), ((160, 96), "centre"), ((64, 64), "principal-point"),
                       ((96, 64), "principal-point")):  # fmt: skip
        config = PairSamplingConfig(size=size, targets=1, crop=crop)
        s = PairDataset(data, [TrainPair(0, (0, 1), (2,))], config)[0]
        if crop == "principal-point":
            scale = max(size[0] / 140, size[1] / 88)
            centre = np.array(size) / 2
            assert np.all(abs(s["context_K"][:, :2, 2].numpy() - centre) <= 0.5 * scale + 1e-9)
        imgs = torch.cat([s["context"], s["target"]]).numpy()
        Ks = torch.cat([s["context_K"], s["target_K"]]).numpy()
        c2ws = torch.cat([s["context_c2w"], s["target_c2w"]]).numpy()
        assert imgs.shape[2:] == (size[1], size[0])
        for img, Kn, T in zip(imgs, Ks, c2ws):
            Xc = np.linalg.inv(T) @ np.append(X, 1.0)
            uv = (Kn @ Xc[:3])[:2] / Xc[2]
            assert abs(_centroid(img[0]) - uv).max() < 0.02, (size, _centroid(img[0]), uv)  # half a pixel: > 0.2
    # the function itself: 160x100 → 80x50 (rows of K halved), then rows 1..48 (cy − 1)
    img, K2 = resize_and_crop(np.zeros((100, 160, 3), np.float32), k, (80, 48))
    assert img.shape == (48, 80, 3)
    expected = k.copy()
    expected[:2] *= 0.5
    expected[1, 2] -= 1.0
    np.testing.assert_allclose(K2, expected, atol=1e-12)


# ------------------------------------------------------------------------------------ bad images
def test_unreadable_image_is_skipped_named_and_counted(
    plane: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    root = tmp_path / "plane"
    shutil.copytree(plane, root)
    data = load_dataset(root)
    pairs = candidate_pairs(data, PairSamplingConfig(size=SMALL))
    bad = data.scenes[0].frames[2]
    bad.image.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")  # after loading: the header check passed
    bad_c2w = torch.from_numpy(bad.camera.cam_to_world.copy())
    counts = []
    for workers in (0, 2):
        ds = PairDataset(data, pairs, PairSamplingConfig(size=SMALL, targets=2), seed=1)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="macsplat_cli.training.data"):
            got = batches(make_loader(ds, batch_size=2, workers=workers, seed=1))
        assert len(got) == 8  # the run goes on: every sample replaced by a readable one
        for b in got:
            for T in torch.cat([b["context_c2w"].flatten(0, 1), b["target_c2w"].flatten(0, 1)]):
                assert not torch.equal(T, bad_c2w)
        assert set(ds.skipped) == {str(bad.image)} and ds.skipped[str(bad.image)] >= 1
        warnings = [r.getMessage() for r in caplog.records if str(bad.image) in r.getMessage()]
        assert len(warnings) == 1 and "unreadable" in warnings[0]
        counts.append(ds.skipped[str(bad.image)])
    assert counts[0] == counts[1]  # counted in the main process, whatever the workers
    for f in data.scenes[0].frames:  # every image unreadable
        f.image.write_bytes(b"garbage")
    ds = PairDataset(data, pairs, PairSamplingConfig(size=SMALL), seed=1)
    with pytest.raises(DatasetError, match="unreadable"):
        batches(make_loader(ds, batch_size=2))
