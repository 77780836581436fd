"""Novel views without holes (issue 15): the far layer beyond both photos, depth-step snapping and camera-facing
discs at steps (no Gaussian bridging an object and its background), both-view fusion, and the fill counts."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.pipeline.background import BackgroundConfig, background_gaussians, background_layer
from macsplat_cli.pipeline.depth import FILL_RULES, FilledDepthMap, estimate_depths, fuse_views, snap_depth_edges
from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig, gaussians_from_depth
from macsplat_cli.pipeline.types import DepthMap, Matches, TwoViewGeometry, View
from macsplat_cli.render import render_camera
from macsplat_cli.report import FillReport, RunReport
from macsplat_cli.rotations import quat_to_rotmat

W, H = 160, 120
WALL_Z = 3.0


@dataclasses.dataclass(frozen=True)
class Pair:
    views: list[View]
    geometry: TwoViewGeometry
    depths: list[DepthMap]
    cams: list[Camera]  # in the synthetic world


def _scene() -> syn.Scene:
    wall = syn.Texture(albedo=(0.5, 0.6, 0.4), seed=3, textured=True, scale=0.7)
    box = syn.Texture(albedo=(0.3, 0.4, 0.7), seed=5, textured=True)
    return syn.Scene(
        [
            syn.Quad((-6.0, -4.0, WALL_Z), (12.0, 0.0, 0.0), (0.0, 8.0, 0.0), wall),
            syn.Box((0.3, 0.2, 2.0), (0.25, 0.25, 0.25), syn.rotation_about((0, 1, 0), 20.0), box),
        ],
        lighting=None,
    )


def _camera(name: str, x: float, look_x: float = 0.0) -> Camera:
    return syn.look_at_camera(name, (x, 0.0, 0.0), (look_x, 0.0, WALL_Z), width=W, height=H, fov_deg=60.0)


def _no_matches() -> Matches:
    return Matches(*(np.zeros((0, 2)),) * 2, np.zeros(0, np.float32), *(np.zeros(0, np.int64),) * 2)


@pytest.fixture(scope="module")
def pair() -> Pair:
    scene = _scene()
    cams = [_camera("a", -0.15), _camera("b", 0.15)]
    rendered = [syn.render(scene, c, supersample=1) for c in cams]
    T = np.linalg.inv(cams[1].cam_to_world) @ cams[0].cam_to_world  # camera 0 → camera 1
    geometry = TwoViewGeometry(T[:3, :3], T[:3, 3], cams[0].K, cams[1].K, _no_matches())
    views = [View(c.name, Path(c.name), r.image, r.mask, c.K, (W, H), "file") for c, r in zip(cams, rendered)]
    depths = [DepthMap(r.depth, (r.depth > 0).astype(np.float32)) for r in rendered]
    return Pair(views, geometry, depths, cams)


def _local(pair: Pair, cam: Camera) -> Camera:
    """``cam`` in the camera-0 world of the reconstruction."""
    return dataclasses.replace(cam, cam_to_world=np.linalg.inv(pair.cams[0].cam_to_world) @ cam.cam_to_world)


def _alpha(g: Gaussians, cam: Camera) -> np.ndarray:
    with torch.no_grad():
        return render_camera(g, cam).alpha.numpy()


# ------------------------------------------------------------------------------------------ the far layer
def test_far_layer_leaves_no_empty_band_beyond_both_photos(pair: Pair) -> None:
    """A target turned 20° past both photos: without the layer a band of it has nothing (alpha < 0.5); with
    it every pixel is covered."""
    maps = gaussians_from_depth(pair.views, pair.geometry, pair.depths)
    scene = Gaussians.cat([m.to_gaussians() for m in maps])
    target = _local(pair, _camera("t", 0.0, look_x=WALL_Z * math.tan(math.radians(20.0))))
    assert (_alpha(scene, target) < 0.5).mean() > 0.1, "the target must see past both photos"
    layer = background_gaussians(pair.views, pair.geometry, pair.depths)
    assert layer.gaussians is not None
    alpha = _alpha(Gaussians.cat([scene, layer.gaussians]), target)
    assert alpha.min() > 0.98
    # counts add up
    c = layer.counts
    assert sum(v for k, v in c.items() if k.startswith(("outside_", "behind_"))) == len(layer.gaussians)
    assert c["outside_view0"] > 0 and c["outside_view1"] > 0 and c["behind_view1"] > 0


def test_far_layer_stays_behind_the_scene_and_off_when_disabled(pair: Pair) -> None:
    """The layer never comes nearer to a camera than the scene it sees (it must not hide the photos), and
    ``enabled=False`` gives no layer (the renderer's flat background shows instead)."""
    layer = background_gaussians(pair.views, pair.geometry, pair.depths, BackgroundConfig(behind=True))
    assert layer.gaussians is not None
    for k in (0, 1):
        T = np.linalg.inv(pair.geometry.cam_to_world(k))
        X = layer.gaussians.means.double().numpy() @ T[:3, :3].T + T[:3, 3]
        K = pair.views[k].K
        uv = (X @ K.T)[:, :2] / X[:, 2:3]
        inside = (X[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        d = pair.depths[k].depth
        scene_z = d[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        assert (X[inside, 2] >= 0.99 * scene_z).all()
    off = background_gaussians(pair.views, pair.geometry, pair.depths, BackgroundConfig(enabled=False))
    assert off.gaussians is None and off.counts == {}


@pytest.mark.parametrize("n", [2, 3])
def test_far_layer_never_hides_what_another_photo_sees_behind_a_near_object(n: int) -> None:
    """A near box before a far wall, three photos 0.4 apart: the layer behind the box (at twice its depth, in front of
    the wall) would hide the wall from the other photos, which see past the box there; those cells are left out, so
    no Gaussian of the layer is nearer to any camera than the surface that camera sees. Two photos keep their layer
    as it was (:data:`~macsplat_cli.pipeline.background.SEEN_THROUGH_MIN_VIEWS`)."""
    wall = syn.Texture(albedo=(0.5, 0.6, 0.4), seed=3, textured=True, scale=0.7)
    box = syn.Texture(albedo=(0.3, 0.4, 0.7), seed=5, textured=True)
    scene = syn.Scene([syn.Quad((-8.0, -6.0, 4.0), (16.0, 0.0, 0.0), (0.0, 12.0, 0.0), wall),
                       syn.Box((0.0, 0.0, 1.2), (0.3, 0.3, 0.3), syn.rotation_about((0, 1, 0), 10.0), box)],
                      lighting=None)  # fmt: skip
    xs = (-0.4, 0.4, 0.0)[:n]
    cams = [syn.look_at_camera(f"c{k}", (x, 0.0, 0.0), (0.0, 0.0, 4.0), width=W, height=H, fov_deg=60.0)
            for k, x in enumerate(xs)]  # fmt: skip
    rendered = [syn.render(scene, c, supersample=1) for c in cams]
    poses = [np.linalg.inv(cams[0].cam_to_world) @ c.cam_to_world for c in cams]  # camera 0's world
    views = [View(c.name, Path(c.name), r.image, r.mask, c.K, (W, H), "file") for c, r in zip(cams, rendered)]
    depths = [DepthMap(r.depth, (r.depth > 0).astype(np.float32)) for r in rendered]
    layer = background_layer(views, [c.K for c in cams], poses, depths)
    assert layer.gaussians is not None and layer.counts["behind_view0"] > 0
    hidden = []
    for k in range(n):
        Tk = np.linalg.inv(poses[k])
        X = layer.gaussians.means.double().numpy() @ Tk[:3, :3].T + Tk[:3, 3]
        uv = (X @ views[k].K.T)[:, :2] / X[:, 2:3]
        inside = (X[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        seen = depths[k].depth[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        hidden.append(int((X[inside, 2] * 1.05 < seen).sum()))
    assert (sum(hidden) == 0) == (n >= 3), hidden


# ------------------------------------------------------------------------------------------ depth steps
def _box_depth(blur: bool) -> np.ndarray:
    """A box (z = 2) in front of a wall (z = 3); ``blur``: the step smeared over 5 pixels, as an upsampling or
    an edge-aware fill leaves it."""
    d = np.full((H, W), 3.0, np.float32)
    d[40:80, 60:100] = 2.0
    if blur:
        inv = 1.0 / d
        k = np.ones(5) / 5
        inv = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, np.pad(inv, 2, mode="edge"))
        inv = np.apply_along_axis(lambda c: np.convolve(c, k, mode="same"), 0, inv)[2:-2, 2:-2]
        d = (1.0 / inv).astype(np.float32)
    return d


def _z_extent(g: Gaussians) -> tuple[np.ndarray, np.ndarray]:
    """Centre z and 2σ reach along z of each Gaussian."""
    R = quat_to_rotmat(torch.nn.functional.normalize(g.quats, dim=-1)).double()
    s = g.log_scales.double().exp()
    cov_zz = ((R[:, 2, :] * s) ** 2).sum(-1)
    return g.means[:, 2].double().numpy(), 2.0 * cov_zz.sqrt().numpy()


@pytest.mark.parametrize("blur", [False, True], ids=["sharp", "smeared"])
def test_no_gaussian_bridges_a_depth_step(pair: Pair, blur: bool) -> None:
    """Box (z = 2) before a wall (z = 3): no Gaussian centre in the gap (more than the 10 % step ratio from
    both sides) and no Gaussian reaching in depth farther than four pixel footprints (fronto-parallel surfaces
    only here). The settings before (no snapping, normals across the step stretching discs along the ray)
    fail one or the other, so the test can fail."""
    view = pair.views[0]
    raw = _box_depth(blur)
    f = float(view.K[0, 0])

    def build(depth: np.ndarray, cfg: GaussianInitConfig) -> Gaussians:
        dm = DepthMap(depth, np.ones_like(depth))
        return gaussians_from_depth([view, view], pair.geometry, [dm, dm], cfg)[0].to_gaussians()

    def bridges(g: Gaussians, footprint: float) -> tuple[int, int]:
        z, reach = _z_extent(g)
        in_gap = (z > 2.0 * 1.05) & (z < 3.0 / 1.05)
        too_deep = reach > 4.0 * footprint * z / f
        return int(in_gap.sum()), int(too_deep.sum())

    cfg = GaussianInitConfig()
    old = bridges(build(raw, GaussianInitConfig(edge_ratio=math.inf)), cfg.footprint)
    snapped, moved = snap_depth_edges(raw, 1.1)
    new = bridges(build(snapped, cfg), cfg.footprint)
    assert new == (0, 0), f"in the gap {new[0]}, reaching across {new[1]}"
    assert old[1] > 0 and (old[0] > 0) == blur
    assert moved.any() == blur
    np.testing.assert_array_equal(snapped[raw == 2.0], 2.0)  # the sides themselves stay put
    np.testing.assert_array_equal(snapped[raw == 3.0], 3.0)


# ------------------------------------------------------------------------------------------ fusion
def test_fusion_drops_a_wrong_filled_layer_and_fixes_a_filled_one_from_the_other_view(pair: Pair) -> None:
    """View 1's filled patch floats 30 % in front of the wall view 0 measured: dropped. View 1's filled patch
    sits 50 % behind the wall that view 0 measured there: it takes view 0's depth."""
    d0, d1 = pair.depths[0].depth.copy(), pair.depths[1].depth.copy()
    meas0 = d0 > 0
    meas1 = d1 > 0
    meas1[10:30, 10:40] = False
    d1[10:30, 10:40] *= 0.7  # wrong, nearer
    meas1[90:110, 110:150] = False
    gt_far = d1[90:110, 110:150].copy()
    d1[90:110, 110:150] *= 1.5  # wrong, farther
    conf = [np.ones_like(d0), np.ones_like(d1)]
    depths, confs, dropped, moved = fuse_views([d0, d1], conf, [meas0, meas1], pair.geometry, 0.05)
    near_patch = dropped[1][10:30, 10:40]
    assert near_patch.mean() > 0.9 and (depths[1][10:30, 10:40][near_patch] == 0).all()
    assert dropped[1].sum() == near_patch.sum() and not dropped[0].any()  # nothing else
    fixed = moved[1][90:110, 110:150]
    assert fixed.mean() > 0.6 and moved[1].sum() == fixed.sum()  # forward warping leaves some pixels unhit
    rel = np.abs(depths[1][90:110, 110:150][fixed] / gt_far[fixed] - 1)
    assert np.median(rel) < 0.02
    np.testing.assert_array_equal(depths[0], d0)  # the measured view is untouched


# ------------------------------------------------------------------------------------------ counts
def test_estimate_depths_counts_every_pixel_once_and_leaves_no_hole() -> None:
    """On a synthetic orbit with its true pose: the rule counts of each view add up to its pixels, the
    measured count is the measured mask, and every pixel inside the mask has a depth unless fusion proved it
    wrong (counted, and rare here)."""
    w, h = 192, 144
    scene = syn.make_scene("object", 0)
    cam0, cam1 = syn.orbit_pair(scene, 10.0, width=w, height=h, seed=1)
    renders = [syn.render(scene, cam0, supersample=1), syn.render(scene, cam1, supersample=1)]
    R, t = syn.relative_pose(cam0, cam1)
    baseline = float(np.linalg.norm(t))
    ys, xs = np.mgrid[0:h:9, 0:w:9]
    grid = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1)
    px1, visible = syn.transfer_points(scene, cam0, cam1, grid)
    n = int(visible.sum())
    inliers = Matches(grid[visible], px1[visible], np.ones(n, np.float32), np.arange(n), np.arange(n))
    geometry = TwoViewGeometry(R, t / baseline, cam0.K.copy(), cam1.K.copy(), inliers)
    views = [
        View(f"v{i}", Path(f"v{i}.png"), r.image, r.mask, c.K.copy(), (w, h), "file")
        for i, (r, c) in enumerate(zip(renders, (cam0, cam1)))
    ]
    depths = estimate_depths(views, geometry)
    for dm, v in zip(depths, views):
        assert isinstance(dm, FilledDepthMap)
        c = dm.fill_counts
        assert sum(c[r] for r in FILL_RULES) == w * h
        assert c["measured"] == int(dm.measured.sum()) > 0
        assert c["none"] == int((dm.depth == 0).sum()) == int((~v.mask).sum()) + c["dropped_free_space"]
        assert c["dropped_free_space"] < 0.1 * v.mask.sum()
    report = RunReport("0", [], {}, {}, [], [], False, {}, None, {}, [], [], 0, {})
    assert "fill" not in report.to_json()
    report.fill = FillReport(depth=[d.fill_counts for d in depths])
    assert report.to_json()["fill"]["depth"][0]["measured"] == depths[0].fill_counts["measured"]


def test_reconstruct_writes_the_far_layer_and_its_counts_and_no_far_layer_leaves_it_out(tmp_path: Path) -> None:
    """End to end from the CLI: the report's ``fill`` section counts every pixel of each view once and the far
    layer's Gaussians; they are in the PLY (``gaussians_written``); ``--no-far-layer`` writes the scene alone."""
    import json

    from macsplat_cli.cameras import CameraSet, save_cameras
    from macsplat_cli.cli import main
    from macsplat_cli.images import save_image

    scene = _scene()
    cams = [_camera("a", -0.15), _camera("b", 0.15)]
    for c in cams:
        save_image(tmp_path / f"{c.name}.png", syn.render(scene, c).image)
    save_cameras(tmp_path / "cams.json", CameraSet(cams))
    reports = {}
    for flag in ("--far-layer", "--no-far-layer"):
        out = tmp_path / flag.strip("-")
        args = [str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--intrinsics", str(tmp_path / "cams.json")]
        got = main(["reconstruct", *args, "-o", str(out / "s.ply"), "--report", str(out / "r.json"), flag, "-q"])
        assert got == 0
        reports[flag] = json.loads((out / "r.json").read_text())
    on, off = reports["--far-layer"], reports["--no-far-layer"]
    layer = sum(n for rule, n in on["fill"]["background"].items() if rule.startswith(("outside_", "behind_")))
    assert off["fill"]["background"] is None and layer > 0
    for counts, image in zip(on["fill"]["depth"], on["images"]):
        w, h = image["working_size"]
        assert sum(counts[r] for r in FILL_RULES) == w * h
    assert on["gaussians"] == on["gaussians_written"] == on["compact"]["after"] + layer
    assert off["gaussians"] == off["gaussians_written"] == off["compact"]["after"]
