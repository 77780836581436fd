"""Synthetic two-view scenes for the tests: ray-traced pairs rendered once per session, their photos on disk, and the
image-plane helpers of the depth tests.

* :func:`rendered_pair` renders the pair a :class:`PairSpec` names, once per test session (cached; the arrays are
  read-only, copy one before changing it): the same generator arguments in two test files give one render.
* The session fixture ``pair_files`` (a :class:`PairFactory`, in ``tests/conftest.py``) writes a pair's photos and
  its true cameras into a session folder, once per (spec, file names); the folder is shared, so a test writes its
  outputs elsewhere (its own ``tmp_path``).
* :func:`orbit_views` gives a pair as the pipeline's :class:`View` objects with the true geometry;
  :func:`room_photos` three photos of a room with their exact depths and cameras (the joint refinement's tests).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.distortion import Distortion
from macsplat_cli.images import save_image

__all__ = [
    "PairFactory",
    "PairFiles",
    "PairSpec",
    "RenderedPair",
    "apply_homography",
    "distorted_photo",
    "orbit_views",
    "pixel_centres",
    "rendered_pair",
    "room_photos",
    "smooth_texture",
    "write_pair",
]


@dataclasses.dataclass(frozen=True)
class PairSpec:
    """The generator arguments of a synthetic pair: ``make_scene(kind, scene_seed, textured=textured)`` seen by
    ``orbit_pair(kind, angle, width, height, fov_deg, seed=orbit_seed)`` (or ``pure_rotation_pair`` with
    ``rotation``), each view rendered with ``supersample``² samples per pixel."""

    kind: syn.SceneKind = "room"
    angle: float = 20.0
    size: tuple[int, int] = (512, 384)  # (W, H)
    fov_deg: float = 60.0
    scene_seed: int = 0
    orbit_seed: int = 0
    textured: bool = True
    rotation: bool = False
    supersample: int = 2


@dataclasses.dataclass(frozen=True)
class RenderedPair:
    """Two rendered views of a :class:`PairSpec` and their true cameras (named ``view0``, ``view1``)."""

    spec: PairSpec
    cams: tuple[Camera, Camera]
    views: tuple[syn.SyntheticView, syn.SyntheticView]  # image [H, W, 3], depth [H, W], normals [H, W, 3]

    @property
    def images(self) -> tuple[np.ndarray, np.ndarray]:
        return self.views[0].image, self.views[1].image

    @property
    def depths(self) -> tuple[np.ndarray, np.ndarray]:
        return self.views[0].depth, self.views[1].depth


def _read_only(view: syn.SyntheticView) -> syn.SyntheticView:
    for a in (view.image, view.depth, view.normals):
        a.setflags(write=False)
    return view


@functools.cache
def rendered_pair(spec: PairSpec) -> RenderedPair:
    """The pair ``spec`` names, rendered once per session (read-only arrays)."""
    scene = syn.make_scene(spec.kind, spec.scene_seed, textured=spec.textured)
    build = syn.pure_rotation_pair if spec.rotation else syn.orbit_pair
    w, h = spec.size
    cams = build(spec.kind, spec.angle, width=w, height=h, fov_deg=spec.fov_deg, seed=spec.orbit_seed)
    views = tuple(_read_only(syn.render(scene, c, supersample=spec.supersample)) for c in cams)
    return RenderedPair(spec, cams, views)  # type: ignore[arg-type]


@dataclasses.dataclass(frozen=True)
class PairFiles:
    """A pair's photos and its true cameras file on disk, with the render they came from."""

    a: Path
    b: Path
    cameras: Path
    rendered: RenderedPair

    @property
    def photos(self) -> tuple[Path, Path]:
        return self.a, self.b


def write_pair(
    folder: Path, spec: PairSpec, names: tuple[str, str] = ("a.png", "b.png"), *, camera_names: bool = False
) -> PairFiles:
    """Write the pair's photos as ``folder/names[i]`` and its true cameras as ``folder/cameras.json`` (the cameras
    keep their names ``view0``, ``view1``; with ``camera_names`` they take the photos' file names)."""
    rendered = rendered_pair(spec)
    cams = rendered.cams
    if camera_names:
        cams = tuple(dataclasses.replace(c, name=n) for c, n in zip(cams, names))  # type: ignore[assignment]
    a, b = (save_image(folder / n, v.image) for n, v in zip(names, rendered.views))
    save_cameras(folder / "cameras.json", CameraSet(list(cams)))
    return PairFiles(a, b, folder / "cameras.json", rendered)


class PairFactory:
    """``pair_files(spec, names=("a.png", "b.png"), camera_names=False)``: :func:`write_pair` into a folder of the
    session, once per set of arguments (the session fixture ``pair_files`` of ``tests/conftest.py``)."""

    def __init__(self, tmp_path_factory: pytest.TempPathFactory) -> None:
        self._tmp = tmp_path_factory
        self._cache: dict[tuple, PairFiles] = {}

    def __call__(
        self, spec: PairSpec, names: tuple[str, str] = ("a.png", "b.png"), *, camera_names: bool = False
    ) -> PairFiles:
        key = (spec, names, camera_names)
        if key not in self._cache:
            self._cache[key] = write_pair(self._tmp.mktemp("pair"), spec, names, camera_names=camera_names)
        return self._cache[key]


# ------------------------------------------------------------------------------ the pipeline's view of a pair
def orbit_views(kind: str, angle: float, w: int = 320, h: int = 240, seed: int = 1):  # noqa: ANN201
    """A ray-traced synthetic orbit pair with its true geometry (unit baseline) and true correspondences as the
    inliers: ``(views, geometry, depths)``, the ground-truth depths in baseline units ([h, w] each)."""
    from macsplat_cli.pipeline.types import Matches, TwoViewGeometry, View

    rendered = rendered_pair(PairSpec(kind, angle, (w, h), orbit_seed=seed))  # type: ignore[arg-type]
    scene = syn.make_scene(kind, 0)  # type: ignore[arg-type]
    cam0, cam1 = rendered.cams
    R, t = syn.relative_pose(cam0, cam1)
    baseline = float(np.linalg.norm(t))
    grid = pixel_centres(w, h)[::37]
    px1, visible = syn.transfer_points(scene, cam0, cam1, grid)
    n = int(visible.sum())
    inliers = Matches(grid[visible], px1[visible], np.ones(n, np.float32), np.arange(n), np.arange(n))
    geometry = TwoViewGeometry(R, t / baseline, cam0.K.copy(), cam1.K.copy(), inliers)
    views = [
        View(f"v{i}", Path(f"v{i}.png"), r.image.copy(), r.mask.copy(), c.K.copy(), (w, h), "file")
        for i, (r, c) in enumerate(zip(rendered.views, (cam0, cam1)))
    ]
    return views, geometry, [r.depth / baseline for r in rendered.views]


def room_photos(w: int = 128, h: int = 96):  # noqa: ANN201
    """Three photos of a textured room 6° apart: ``(views, depths, poses)``, the exact depths [h, w] float32 and
    the cameras' camera-to-world [4, 4] (camera 0 the world frame)."""
    from macsplat_cli.pipeline.types import View

    scene = syn.make_scene("room", 1)
    cams = syn.orbit_cameras(scene, [-6.0, 0.0, 6.0], width=w, height=h, fov_deg=60.0,
                             names=[f"v{k}.png" for k in range(3)])  # fmt: skip
    ref = np.linalg.inv(cams[0].cam_to_world)
    views, depths, poses = [], [], []
    for c in cams:
        r = syn.render(scene, c, supersample=2)
        views.append(View(c.name, Path(c.name), r.image.astype(np.float32), np.ones((h, w), bool), c.K.copy(),
                          (w, h), "file"))  # fmt: skip
        depths.append(r.depth.astype(np.float32))
        poses.append(ref @ c.cam_to_world)
    return views, depths, poses


# ------------------------------------------------------------------------------ image-plane helpers
def smooth_texture(rng: np.random.Generator):  # noqa: ANN201
    """A smooth random texture over continuous pixel coordinates (sum of sinusoids, periods 5–25 px):
    ``tex(xy [N, 2]) → [N]`` float32."""
    freq = rng.uniform(-1, 1, (12, 2))
    freq *= (2 * np.pi / rng.uniform(5, 25, 12))[:, None] / np.linalg.norm(freq, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, 12)

    def tex(xy: np.ndarray) -> np.ndarray:
        return (0.5 + 0.1 * np.sin(xy @ freq.T + phase).sum(-1)).astype(np.float32)

    return tex


def pixel_centres(w: int, h: int) -> np.ndarray:
    """Pixel centres (x + 0.5, y + 0.5), row-major. [h·w, 2]"""
    ys, xs = np.mgrid[0:h, 0:w]
    return np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)


def apply_homography(Hm: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``xy`` [N, 2] mapped by the 3×3 homography ``Hm``. [N, 2]"""
    p = np.c_[xy, np.ones(len(xy))] @ Hm.T
    return p[:, :2] / p[:, 2:]


def distorted_photo(scene: syn.Scene, cam: Camera, d: Distortion, margin: int = 96) -> np.ndarray:
    """``cam``'s photo through lens ``d``: each distorted pixel sampled (bilinear) from a pinhole render of a frame
    ``margin`` pixels wider on every side, at the undistorted position (asserted inside it). [H, W, 3]"""
    W, H, MARGIN = cam.width, cam.height, margin
    K = cam.K.copy()
    K[:2, 2] += MARGIN
    wide = Camera("wide", W + 2 * MARGIN, H + 2 * MARGIN, K, cam.cam_to_world)
    pinhole = syn.render(scene, wide, supersample=3).image
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    K_cv = cam.K.copy()
    K_cv[:2, 2] -= 0.5  # OpenCV's pixel centres are on integers
    pts = np.stack([j - 0.5, i - 0.5], -1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, K_cv, np.array(d.coeffs), P=K_cv).reshape(H, W, 2) + MARGIN
    assert und.min() > 0 and und[..., 0].max() < W + 2 * MARGIN - 1 and und[..., 1].max() < H + 2 * MARGIN - 1
    return cv2.remap(pinhole, und[..., 0].astype(np.float32), und[..., 1].astype(np.float32), cv2.INTER_LINEAR)
