"""Scene compaction (:mod:`macsplat_cli.pipeline.compact`) on ray-traced pairs with exact depth.

The per-pixel Gaussians come from the pipeline's own Gaussian stage (``gaussians_from_depth``) fed with
the ray-traced depth, so every test runs in a fraction of a second and knows the true surface: a wall
whose left half is a flat colour and right half textured, a textured box in front of it (depth edges),
seen by two cameras 0.3 m apart and rendered from a third camera between them.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import InputError
from macsplat_cli.gaussians import GaussianMaps
from macsplat_cli.metrics import psnr
from macsplat_cli.pipeline.compact import CompactConfig, CompactReport, compact, compact_reconstruction
from macsplat_cli.pipeline.gaussian_init import gaussians_from_depth
from macsplat_cli.pipeline.types import DepthMap, Matches, TwoViewGeometry, View
from macsplat_cli.presets import compact_config
from macsplat_cli.render import render_camera

from support.scenes import PairFactory, PairSpec

W, H = 160, 120
WALL_Z = 3.0
PSNR_LOSS_DB = 0.2  # the target on novel views (default settings)


@dataclasses.dataclass(frozen=True)
class Pair:
    maps: list[GaussianMaps]
    cameras: list[Camera]  # working-size cameras in the camera-0 world
    images: list[np.ndarray]
    novel: Camera  # between the two, camera-0 world
    novel_image: np.ndarray
    depth0: np.ndarray  # ray-traced depth of view 0 [H, W]


def _scene() -> syn.Scene:
    flat = syn.Texture(albedo=(0.55, 0.35, 0.25), textured=False)
    tex = syn.Texture(albedo=(0.5, 0.6, 0.4), seed=3, textured=True, scale=0.7)
    box_tex = syn.Texture(albedo=(0.3, 0.4, 0.7), seed=5, textured=True)
    return syn.Scene(
        [
            syn.Quad((-4.0, -3.0, WALL_Z), (4.0, 0.0, 0.0), (0.0, 6.0, 0.0), flat),  # left half, x ∈ [-4, 0]
            syn.Quad((0.0, -3.0, WALL_Z), (4.0, 0.0, 0.0), (0.0, 6.0, 0.0), tex),  # right half
            syn.Box((0.55, 0.35, 2.2), (0.2, 0.2, 0.2), syn.rotation_about((0, 1, 0), 30.0), box_tex),
        ],
        lighting=None,
    )


def _camera(name: str, x: float) -> Camera:
    return syn.look_at_camera(name, (x, 0.0, 0.0), (0.0, 0.0, WALL_Z), width=W, height=H, fov_deg=60.0)


@pytest.fixture(scope="module")
def pair() -> Pair:
    scene = _scene()
    cams = [_camera("a", -0.15), _camera("b", 0.15)]
    rendered = [syn.render(scene, c) for c in cams]
    T = np.linalg.inv(cams[1].cam_to_world) @ cams[0].cam_to_world  # camera 0 → camera 1
    no_matches = Matches(*(np.zeros((0, 2)),) * 2, np.zeros(0, np.float32), *(np.zeros(0, np.int64),) * 2)
    geometry = TwoViewGeometry(T[:3, :3], T[:3, 3], cams[0].K, cams[1].K, no_matches)
    views = [
        View(c.name, Path(c.name), r.image, r.mask, c.K, (W, H), "file") for c, r in zip(cams, rendered)
    ]  # fmt: skip
    depths = [DepthMap(r.depth, (r.depth > 0).astype(np.float32)) for r in rendered]
    maps = gaussians_from_depth(views, geometry, depths)
    world = [dataclasses.replace(c, cam_to_world=geometry.cam_to_world(k)) for k, c in enumerate(cams)]
    novel = _camera("n", 0.02)
    novel_local = dataclasses.replace(novel, cam_to_world=np.linalg.inv(cams[0].cam_to_world) @ novel.cam_to_world)
    novel_image = syn.render(scene, novel).image
    return Pair(maps, world, [r.image for r in rendered], novel_local, novel_image, rendered[0].depth)


def _render(g, cam: Camera) -> np.ndarray:  # noqa: ANN001
    with torch.no_grad():
        return np.clip(render_camera(g, cam).rgb.numpy(), 0.0, 1.0)


def _only(**on: object) -> CompactConfig:
    """Every optional step off, then ``on``."""
    cfg = compact_config("best")
    return dataclasses.replace(cfg, name="test", **on)


def _full(pair: Pair):  # noqa: ANN202
    from macsplat_cli.gaussians import Gaussians

    return Gaussians.cat([m.to_gaussians() for m in pair.maps])


# ------------------------------------------------------------------------------------------ steps
def test_dedup_merges_the_surface_both_views_see(pair: Pair) -> None:
    g, report = compact(pair.maps, pair.cameras, _only(dedup=True))
    n0, n1 = (int(m.valid_mask().sum()) for m in pair.maps)
    step = {s.name: s for s in report.steps}["dedup"]
    merged = step.before - step.after
    assert merged > 0.6 * n1, "most of view 1 looks at the wall view 0 sees too"
    assert len(g) == n0 + n1 - merged
    # view 0's pixels come first, row-major, all still there: the merged ones moved half-way to view 1's
    before0 = pair.maps[0].to_gaussians().means
    moved = (g.means[:n0] - before0).norm(dim=1)
    foot = WALL_Z / pair.cameras[0].K[0, 0]  # one pixel on the wall, metres
    assert int((moved > 1e-6).sum()) > 0.5 * n0
    assert float(moved.max()) < 0.02 * 5.0  # within the depth tolerance at the farthest depth
    # each merged view-1 Gaussian is close to the view-0 Gaussian that absorbed it
    from macsplat_cli.camera_math import project_points
    from macsplat_cli.pipeline.compact.state import view_states

    v0 = view_states(pair.maps[:1], pair.cameras[:1], None)[0]
    X1 = pair.maps[1].to_gaussians().means.double()
    col, row, z, inside = project_points(X1, torch.linalg.inv(v0.c2w), v0.K, v0.size)
    d = (g.means[:n0].double()[row * W + col] - X1).norm(dim=1)
    assert float(d[inside].median()) < 2.0 * foot


def test_flat_regions_merge_while_texture_and_edges_keep_full_density(pair: Pair) -> None:
    m = pair.maps[0]
    g, report = compact([m], pair.cameras[:1], _only(adaptive=True))
    cam = pair.cameras[0]
    X = g.means.double().numpy() @ np.linalg.inv(cam.cam_to_world)[:3, :3].T
    uv = (X @ cam.K.T)[:, :2] / X[:, 2:]
    depth = X[:, 2]
    wall = np.abs(depth - WALL_Z) < 0.3
    # the box projects around u ≈ 110; keep away from it and from the seam at u = W/2
    flat = wall & (uv[:, 0] < W / 2 - 8)
    textured = wall & (uv[:, 0] > W / 2 + 8) & ((uv[:, 0] > 140) | (uv[:, 1] < 20) | (uv[:, 1] > 100))
    flat_px = (W / 2 - 8) * H
    assert flat.sum() < flat_px / 8, "flat wall: mostly 4×4 blocks or larger"
    scales = g.scales.numpy().max(1)
    assert np.median(scales[flat]) > 3 * WALL_Z / cam.K[0, 0], "merged Gaussians cover blocks"
    tex_px = int(np.sum(textured))
    tex_area = (W - 140) * (100 - 20) + (W - (W / 2 + 8)) * 40
    # ~70 % of its 2×2 blocks vary by more than the default colour tolerance (0.06): those keep a Gaussian
    # per pixel, the rest merge into small blocks
    assert tex_px > 0.6 * tex_area, "textured wall keeps most of its per-pixel Gaussians"
    assert tex_px / tex_area > 5 * flat.sum() / flat_px
    # no merged Gaussian hangs over a depth edge into the background (a fattened silhouette): across its extent
    # the true surface is never much farther than the Gaussian. (A wall block may reach behind the box: hidden.)
    minor = g.scales.sort(1).values[:, 1].numpy()  # a pixel Gaussian's: 0.7 px (only its tilt axis stretches)
    big = minor > 1.2 * depth / cam.K[0, 0]
    assert big.sum() > 100
    # its standard deviations along the image axes (EWA: J Σ Jᵀ), ≈ the half-width of the block it replaced
    R = np.linalg.inv(cam.cam_to_world)[:3, :3]
    cov = R @ g.covariances().double().numpy()[big] @ R.T
    f, x, z = cam.K[0, 0], X[big], depth[big]
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = f / z
    J[:, :, 2] = -f * x[:, :2] / z[:, None] ** 2
    std = np.sqrt(np.diagonal(J @ cov @ J.transpose(0, 2, 1), axis1=1, axis2=2))  # [M, 2] px
    for du, dv in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        u = np.clip(uv[big, 0] + du * std[:, 0], 0, W - 1).astype(int)
        v = np.clip(uv[big, 1] + dv * std[:, 1], 0, H - 1).astype(int)
        bad = pair.depth0[v, u] - z >= 0.15 * z  # box → wall: ≥ 30 %; a crease between faces is no edge
        assert not bad.any(), (uv[big][bad], z[bad], pair.depth0[v, u][bad])
    step = {s.name: s for s in report.steps}["adaptive"]
    assert step.after < step.before


def test_budget_is_exact_and_keeps_the_important_gaussians(pair: Pair) -> None:
    full, _ = compact(pair.maps, pair.cameras, CompactConfig())
    budget = len(full) // 3
    g, report = compact(pair.maps, pair.cameras, CompactConfig(budget=budget))
    assert len(g) == budget == report.after
    assert report.steps[-1].name == "budget" and report.steps[-1].before == len(full)
    # the dropped ones are the small ones: the kept ones' median size exceeds the whole set's
    assert float(g.scales.amax(1).median()) >= float(full.scales.amax(1).median())
    assert len(compact(pair.maps, pair.cameras, CompactConfig(budget=0))[0]) == 0


def test_best_preset_renders_the_same_picture(pair: Pair) -> None:
    full = _full(pair)
    g, report = compact(pair.maps, pair.cameras, compact_config("best"))
    assert len(g) == len(full) == report.before == report.after
    for a, b in zip(g.tensors(), full.tensors()):
        assert torch.equal(a, b)  # the very same Gaussians as the maps' own conversion
    diff = np.abs(_render(g, pair.novel) - _render(full, pair.novel)).max()
    assert diff == 0.0  # (a) bitwise the same Gaussians, the same renderer call: the same picture


def test_balanced_keeps_the_novel_view_and_removes_most_gaussians(pair: Pair) -> None:
    full = _full(pair)
    g, report = compact(pair.maps, pair.cameras, compact_config("balanced"), images=pair.images)
    g.check_finite()
    assert report.ratio >= 3.0
    p_full = psnr(_render(full, pair.novel), pair.novel_image)
    p_cmp = psnr(_render(g, pair.novel), pair.novel_image)
    assert p_cmp >= p_full - PSNR_LOSS_DB, (p_full, p_cmp)
    _, rep_fast = compact(pair.maps, pair.cameras, compact_config("fast"))
    assert rep_fast.after < report.after


def test_non_finite_and_invisible_gaussians_are_removed(pair: Pair) -> None:
    m = pair.maps[0].detach()
    m.means[0, 5, 7] = float("nan")
    m.log_scales[0, 9, 9, 1] = float("inf")
    m.opacity_logits[0, 20, 30] = -20.0  # opacity 2e-9: the renderer culls it
    g, report = compact([m], pair.cameras[:1], compact_config("best"))
    g.check_finite()
    assert report.before - report.after == 3
    assert report.steps[0].name == "prune_opacity" and report.steps[0].after == report.before - 3


def test_sh_bands_that_do_not_matter_are_dropped(pair: Pair) -> None:
    m = pair.maps[0].detach()
    b, h, w = m.batch, *m.size
    sh = torch.zeros(b, h, w, 16, 3)
    sh[..., 0, :] = m.sh[..., 0, :]
    sh[..., 1:, :] = 1e-4 * torch.randn(b, h, w, 15, 3, generator=torch.Generator().manual_seed(0))
    quiet = dataclasses.replace(m, sh=sh)
    g, report = compact([quiet], pair.cameras[:1], _only(sh="auto"))
    assert report.sh_degree_before == 3 and g.sh_degree == 0
    loud = sh.clone()
    loud[..., 1:4, :] = 0.5  # strong degree-1 view dependence
    g, _ = compact([dataclasses.replace(m, sh=loud)], pair.cameras[:1], _only(sh="auto"))
    assert g.sh_degree >= 1
    padded = torch.zeros_like(sh)
    padded[..., :4, :] = loud[..., :4, :]  # degree 1 stored as degree 3
    g, report = compact([dataclasses.replace(m, sh=padded)], pair.cameras[:1], compact_config("best"))
    assert g.sh_degree == 1 and report.after == report.before


def test_report_and_inputs(pair: Pair) -> None:
    g, report = compact(pair.maps, pair.cameras)
    d = json.loads(json.dumps(report.to_dict()))
    assert d["before"] == sum(int(m.valid_mask().sum()) for m in pair.maps) and d["after"] == len(g)
    for a, b in zip(report.steps, report.steps[1:]):
        assert a.after == b.before
    assert all(s.reason for s in report.steps)
    assert isinstance(report, CompactReport) and report.seconds < 5.0
    with pytest.raises(InputError):
        compact(pair.maps, pair.cameras[:1])
    with pytest.raises(InputError):
        compact_config("ultra")
    with pytest.raises(InputError):
        compact(pair.maps, pair.cameras, CompactConfig(max_block=3))


def test_compact_config_is_the_one_home_of_the_quality_presets() -> None:
    """Every quality has its compaction settings; the name is reported, the budget passed through."""
    assert compact_config("balanced") == CompactConfig()
    fast, best = compact_config("fast", budget=10), compact_config("best")
    assert (fast.name, fast.max_block, fast.prune_occluded, fast.subpixel_px) == ("fast", 16, False, 0.0)
    assert fast.budget == 10
    assert (best.name, best.adaptive, best.dedup, best.prune_floaters, best.sh) == ("best", False, False, False, "zero")
    with pytest.raises(InputError, match="--quality 'ultra': use fast, balanced, best"):
        compact_config("ultra")  # type: ignore[arg-type]


def test_pooled_maps_use_rescaled_cameras(pair: Pair) -> None:
    """Refined maps are pooled (smaller than the photos): the cameras are rescaled to them."""
    pooled = [m.pooled(2) for m in pair.maps]
    full = _full(dataclasses.replace(pair, maps=pooled))
    g, report = compact(pooled, pair.cameras, images=pair.images)
    assert report.ratio > 1.5
    p_full = psnr(_render(full, pair.novel), pair.novel_image)
    assert psnr(_render(g, pair.novel), pair.novel_image) >= p_full - PSNR_LOSS_DB


def test_compact_reconstruction_on_an_engine_run(pair_files: PairFactory) -> None:
    from macsplat_cli.engine import EngineConfig, reconstruct
    from macsplat_cli.pipeline.run import count_gaussians
    from macsplat_cli.presets import Overrides

    files = pair_files(PairSpec("room", 12.0, (192, 144), 60.0, scene_seed=5))
    rec = reconstruct([files.a, files.b], EngineConfig(overrides=Overrides(size=192)))
    g, report = compact_reconstruction(rec)
    assert report.before == count_gaussians(rec.maps) and len(g) == report.after < 0.7 * report.before
    assert math.isfinite(report.ratio)
    g.check_finite()


# ------------------------------------------------------------------------------------------ spatial index
def _turned(pair: Pair, k: int) -> tuple[GaussianMaps, Camera]:
    """View ``k`` turned round on the spot (180° about its y axis): its Gaussians lie behind the other cameras, and
    theirs behind it."""
    c2w = np.asarray(pair.cameras[k].cam_to_world) @ np.diag([-1.0, 1.0, -1.0, 1.0])
    m = pair.maps[k]
    turned = dataclasses.replace(m, cam_to_world=torch.as_tensor(c2w, dtype=m.dtype)[None])
    return turned, dataclasses.replace(pair.cameras[k], cam_to_world=c2w)


def test_view_steps_project_only_what_each_camera_can_see(pair: Pair, monkeypatch: pytest.MonkeyPatch) -> None:
    from macsplat_cli.pipeline.compact import run as compact_run
    from macsplat_cli.pipeline.compact.cleanup import prune_occluded_reference
    from macsplat_cli.pipeline.compact.state import ViewState

    away_map, away_cam = _turned(pair, 1)
    projected = {True: 0, False: 0}  # into the turned camera, into the others
    real = ViewState.project

    def counting(self: ViewState, points: torch.Tensor):  # noqa: ANN202
        projected[bool(self.c2w[2, 2] < 0)] += len(points)
        return real(self, points)

    monkeypatch.setattr(ViewState, "project", counting)
    monkeypatch.setattr(compact_run, "prune_occluded", prune_occluded_reference)  # the kernel projects all
    only_occlusion = CompactConfig(prune_floaters=False, dedup=False, subpixel_px=0.0, adaptive=False, sh="keep")
    _, report = compact([*pair.maps, away_map], [*pair.cameras, away_cam], only_occlusion)
    assert report.steps[-1].name == "prune_occluded" and report.before > 2.5 * W * H
    # each camera projects its own side's Gaussians only (every view's, 3 × 3 map's worth, without the index)
    assert projected[True] <= W * H and projected[False] <= 2 * 2 * W * H
    projected.update({True: 0, False: 0})
    only_subpixel = dataclasses.replace(only_occlusion, prune_occluded=False, subpixel_px=0.1)
    compact([*pair.maps, away_map], [*pair.cameras, away_cam], only_subpixel)
    assert projected[True] <= W * H  # the sub-pixel step: a Gaussian's own view settles it, no other is tried


def test_the_occlusion_kernel_prunes_what_its_pytorch_twin_prunes(pair: Pair, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 40: the occlusion step's Numba kernels (the cameras' z-buffers, then each Gaussian until a camera sees
    it) leave the twin's Gaussians alive (they sum the projection in their own order: a centre on a pixel edge or
    the depth tolerance may round the other way, at most one in ten thousand), on views that hide Gaussians (the
    box's shadow on the wall, a camera turned away, a copy of a view behind it); one kernel thread or two, the same
    bits."""
    from macsplat_cli import _threads
    from macsplat_cli.pipeline.compact import cleanup
    from macsplat_cli.pipeline.compact.state import view_states

    away_map, away_cam = _turned(pair, 1)
    back = pair.maps[0].detach()
    back.means[0, :, :, 2] *= 1.2  # view 0's surface again, behind the wall: hidden from every camera
    maps, cams = [*pair.maps, away_map, back], [*pair.cameras, away_cam, pair.cameras[0]]
    cfg = CompactConfig()

    def alive(prune) -> list[torch.Tensor]:  # noqa: ANN001
        views = view_states(maps, cams, None)
        prune(views, cfg)
        return [v.alive.clone() for v in views]

    got, ref = alive(cleanup.prune_occluded), alive(cleanup.prune_occluded_reference)
    total = sum(int(m.valid_mask().sum()) for m in maps)
    differ = sum(int((g != r).sum()) for g, r in zip(got, ref))
    assert differ <= max(1, total // 10_000), (differ, total)
    pruned = [int(m.valid_mask().sum()) - int(g.sum()) for m, g in zip(maps, got)]
    assert pruned[3] > 0.9 * int(back.valid_mask().sum()) and 0 < pruned[0] < 0.2 * W * H, pruned
    monkeypatch.setattr(_threads, "kernel_threads", lambda: 1)
    assert all(torch.equal(a, b) for a, b in zip(alive(cleanup.prune_occluded), got))


def test_the_spatial_index_changes_no_output(pair: Pair, monkeypatch: pytest.MonkeyPatch) -> None:
    from macsplat_cli.pipeline.compact import cull

    maps = [*pair.maps, _turned(pair, 1)[0], _turned(pair, 0)[0]]
    cams = [*pair.cameras, _turned(pair, 1)[1], _turned(pair, 0)[1]]
    g, report = compact(maps, cams, images=[*pair.images, *pair.images])
    monkeypatch.setattr(cull, "_box_in_frustum", lambda lo, *camera: torch.ones(len(lo), dtype=torch.bool))
    g_all, report_all = compact(maps, cams, images=[*pair.images, *pair.images])  # every Gaussian into every view
    assert [(s.name, s.after) for s in report.steps] == [(s.name, s.after) for s in report_all.steps]
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(g, name), getattr(g_all, name))


def test_tiles_keep_every_gaussian_a_camera_sees(pair: Pair) -> None:
    from macsplat_cli.pipeline.compact.cull import view_tiles
    from macsplat_cli.pipeline.compact.state import view_states

    views = view_states(pair.maps, pair.cameras, None)
    v = views[0]
    idx = v.alive.reshape(-1).nonzero().squeeze(1)
    X = v.world_means().reshape(-1, 3)[idx]
    tiles = view_tiles(idx, X, v.size[1])
    rng = np.random.default_rng(0)
    culled = 0
    for trial in range(40):  # the views' own cameras, turned and moved: a frustum edge through the wall
        cam = views[trial % 2]
        c2w = cam.c2w.clone()
        angle = np.radians(rng.uniform(-60, 60))
        c, s = np.cos(angle), np.sin(angle)
        c2w[:3, :3] = c2w[:3, :3] @ torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
        c2w[:3, 3] += torch.as_tensor(rng.normal(0, 0.5, 3))
        moved = dataclasses.replace(cam, c2w=c2w)
        inside = moved.project(X)[3]
        sel = tiles.seen_by(moved)
        chosen = torch.zeros(len(X), dtype=torch.bool)
        chosen[sel] = True
        assert not (inside & ~chosen).any()
        culled += int((~chosen).sum())
    assert culled > 0


def test_the_box_test_is_the_eight_corner_test() -> None:
    """The frustum test of a tile's world box from its centre and half-extent (one product) says what evaluating
    the five half-spaces at the box's 8 corners says (an affine function is largest at a corner)."""
    from macsplat_cli.camera_math import NEAR_Z
    from macsplat_cli.pipeline.compact import cull

    g = torch.Generator().manual_seed(0)
    h, w, m = 48, 64, cull._MARGIN_PX
    K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    bits = torch.tensor([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=torch.bool)
    for trial in range(20):
        angle = 0.5 * trial
        c, s = math.cos(angle), math.sin(angle)
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
        w2c[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64)
        lo = 3 * torch.randn(500, 3, generator=g, dtype=torch.float64)
        hi = lo + torch.rand(500, 3, generator=g, dtype=torch.float64)
        corners = torch.where(bits, hi[:, None], lo[:, None])  # [T, 8, 3]
        X = corners @ w2c[:3, :3].T + w2c[:3, 3]
        KX, z = X @ K.T, X[..., 2]
        halves = (
            z - NEAR_Z,
            KX[..., 0] + m * z,
            (w + m) * z - KX[..., 0],
            KX[..., 1] + m * z,
            (h + m) * z - KX[..., 1],
        )
        ref = torch.stack([f.amax(1) > 0 for f in halves]).all(0)
        got = cull._box_in_frustum(lo, hi, w2c, K, (h, w))
        assert torch.equal(got, ref)
        assert 0 < int(got.sum()) < len(got)


def test_dedup_tries_the_view_that_takes_most_first(pair: Pair, monkeypatch: pytest.MonkeyPatch) -> None:
    from macsplat_cli.pipeline.compact import dedup as dedup_module
    from macsplat_cli.pipeline.compact.state import ViewState, view_states

    # view 0 keeps only its left fifth alive; views 1 and 2 are the same photo: view 2 belongs to view 1
    maps, cams = [pair.maps[0], pair.maps[1], pair.maps[1]], [pair.cameras[0], pair.cameras[1], pair.cameras[1]]
    views = view_states(maps, cams, None)
    views[0].alive[..., W // 5 :] = False
    projected = [0]
    real = ViewState.project

    def counting(self: ViewState, points: torch.Tensor):  # noqa: ANN202
        projected[0] += len(points)
        return real(self, points)

    monkeypatch.setattr(ViewState, "project", counting)
    monkeypatch.setattr(dedup_module, "_mergeable", dedup_module._mergeable_reference)  # it projects with `project`
    n2 = int(views[2].alive.sum())
    dedup_module.dedup(views, _only(dedup=True))
    assert int(views[2].alive.sum()) < 0.05 * n2  # merged, into view 1 where it is alive
    # view 1 into view 0 (all of it), then view 2 into view 1 (all of it) and the few left into view 0; in photo order
    # view 2 went through view 0 first, where almost nothing merges: ~3 views' worth
    assert projected[0] < 2.3 * W * H


def test_the_dedup_kernel_merges_what_its_pytorch_twin_merges(pair: Pair, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 40: the dedup step's Numba test gives its twin's answers (the projection summed in its own order: a
    centre on a pixel edge or a tolerance may round the other way, at most one in ten thousand), and the step leaves
    the same Gaussians, merged the same way, on views that merge both ways (a repeat of a view, a view seen from the
    other side of the pair); one kernel thread or two, the same bits."""
    from macsplat_cli import _threads
    from macsplat_cli.pipeline.compact import dedup as dedup_module
    from macsplat_cli.pipeline.compact.state import view_states

    maps, cams = [pair.maps[0], pair.maps[1], pair.maps[0]], [pair.cameras[0], pair.cameras[1], pair.cameras[0]]
    views = view_states(maps, cams, None)
    idx = torch.arange(W * H)
    world = views[1].world_means().reshape(-1, 3)
    got = dedup_module._mergeable(views[1], views[0], idx, world, _only(dedup=True))
    ref = dedup_module._mergeable_reference(views[1], views[0], idx, world, _only(dedup=True))
    assert int((got[0] != ref[0]).sum()) <= 1 and torch.equal(got[3], ref[3])
    assert 0.3 * W * H < int(got[0].sum()) < int(got[3].sum()) <= W * H  # merges, and not everything inside does
    assert torch.equal(got[1][ref[0]], ref[1][ref[0]]) and torch.equal(got[2][ref[0]], ref[2][ref[0]])

    def run() -> list[torch.Tensor]:
        vs = view_states(maps, cams, None)
        dedup_module.dedup(vs, _only(dedup=True))
        return [t for v in vs for t in (v.alive, v.means, v.sh, v.logits)]

    kernel = run()
    monkeypatch.setattr(dedup_module, "_mergeable", dedup_module._mergeable_reference)
    assert all(torch.equal(a, b) for a, b in zip(kernel, run()))
    monkeypatch.undo()  # the kernel again
    monkeypatch.setattr(_threads, "kernel_threads", lambda: 1)
    assert all(torch.equal(a, b) for a, b in zip(kernel, run()))


def test_the_sh_step_compares_colours_from_the_eyes_of_many_photos() -> None:
    """60 photos give 1,830 eyes (cameras and midpoints); 9,300 Gaussians × 1,830 eyes is past ``torch.quantile``'s
    2²⁴ values, which stopped a 16-photo set of the orbit with an internal error: the step compares fewer Gaussians
    instead, and still keeps a band that changes the colour across the views."""
    from types import SimpleNamespace

    from macsplat_cli.gaussians import Gaussians
    from macsplat_cli.pipeline.compact.sh_degree import sh_degree

    n, gen = 9_300, torch.Generator().manual_seed(0)
    sh = torch.zeros(n, 4, 3)
    sh[:, 0] = 0.5
    sh[:, 1:] = 0.3 * torch.randn(n, 3, 3, generator=gen)
    g = Gaussians(torch.randn(n, 3, generator=gen), torch.zeros(n, 3), torch.tensor([1.0, 0, 0, 0]).expand(n, 4),
                  torch.zeros(n), sh)  # fmt: skip
    angles = torch.linspace(0, 2 * math.pi, 61, dtype=torch.float64)[:-1]
    cams = []
    for a in angles:
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, 3] = torch.stack([5 * torch.cos(a), torch.zeros(()), 5 * torch.sin(a)])
        cams.append(SimpleNamespace(c2w=c2w))
    degree, why = sh_degree(g, cams, CompactConfig())  # type: ignore[arg-type]
    assert degree == 1, why


def test_the_sh_steps_quantile_is_torch_quantiles_bits() -> None:
    """``sh_degree.quantile`` (two order statistics) against ``torch.quantile`` (a sort): equal bits on random sizes,
    skews and ties, NaN propagated; the rank and weight in float64 instead would differ in the last bit on some."""
    from macsplat_cli.pipeline.compact.sh_degree import quantile

    gen = torch.Generator().manual_seed(0)
    for _ in range(300):
        n = int(torch.randint(1, 5000, (), generator=gen))
        x = torch.rand(n, generator=gen) ** float(torch.rand((), generator=gen) * 4 + 0.2)
        if n % 3 == 0:
            x = torch.round(x * 10) / 10  # ties
        for q in (0.95, 0.5, 0.0, 1.0):
            assert quantile(x, q).item() == torch.quantile(x, q).item(), (n, q)
    x = torch.rand(100, generator=gen)
    x[17] = float("nan")
    assert math.isnan(quantile(x, 0.95).item()) and math.isnan(torch.quantile(x, 0.95).item())
