"""The analytic ray caster: first hits of camera rays, rendered views with exact depth and normals, correspondences."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...cameras import Camera
from ...errors import InputError
from .primitives import _EPS_T, _dot
from .scenes import Scene

__all__ = ["RayHits", "SyntheticView", "cast_rays", "render", "transfer_points"]


@dataclass
class RayHits:
    """First hits of camera rays.

    Attributes:
        depth: camera-space z of the hit, 0 where the ray hits nothing. [N] float64
        points: world hit points (NaN where nothing is hit). [N, 3] float64
        normals: world unit normals facing the camera (0 where nothing is hit). [N, 3] float64
        color: shaded RGB in [0, 1] (the background where nothing is hit). [N, 3] float32
        primitive: index into ``scene.primitives`` of the surface hit, −1 for none. [N] int32
    """

    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    color: np.ndarray
    primitive: np.ndarray


def _pixel_rect(camera: Camera, centre: np.ndarray, radius: float) -> tuple[float, float, float, float] | None:
    """Pixel rectangle ``(x0, x1, y0, y1)`` containing the projection of a sphere, or None if unbounded."""
    corners = centre + radius * np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    cam = corners @ camera.R.T + camera.t
    if (cam[:, 2] <= 0).all():  # wholly behind the camera: an empty rectangle
        return math.inf, -math.inf, math.inf, -math.inf
    if (cam[:, 2] < 1e-3).any():
        return None
    proj = cam @ camera.K.T
    xy = proj[:, :2] / proj[:, 2:]
    return float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max())


def cast_rays(scene: Scene, camera: Camera, pixels: np.ndarray) -> RayHits:
    """Cast camera rays through continuous pixel coordinates and shade the first hits.

    Args:
        scene: the scene.
        camera: the camera (pixel centres at ``+0.5``: pixel (row i, column j) is at
            ``(j + 0.5, i + 0.5)``).
        pixels: ``(x, y)`` image coordinates. [N, 2]

    Returns:
        The first hit of each ray.
    """
    pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    return _cast(scene, camera, np.ascontiguousarray(pix[:, 0]), np.ascontiguousarray(pix[:, 1]), True)


def _cast(scene: Scene, camera: Camera, px: np.ndarray, py: np.ndarray, geometry: bool) -> RayHits:
    """:func:`cast_rays` on coordinates ``px``, ``py`` [N]; without ``geometry``, ``points``/``normals`` are empty."""
    n = len(px)
    Ki = np.linalg.inv(camera.K)
    c2w = camera.cam_to_world
    R, origin = c2w[:3, :3], c2w[:3, 3].copy()
    # camera-space direction (x, y, 1): the ray parameter t is the depth z
    dcx = Ki[0, 0] * px + Ki[0, 1] * py + Ki[0, 2]
    dcy = Ki[1, 1] * py + Ki[1, 2]
    dirs = np.empty((3, n))
    for k in range(3):
        dirs[k] = R[k, 0] * dcx + R[k, 1] * dcy + R[k, 2]
    best_t = np.full(n, np.inf)
    best_prim = np.full(n, -1, dtype=np.int32)
    best_face = np.zeros(n, dtype=np.int8)
    for i, prim in enumerate(scene.primitives):
        rect = _pixel_rect(camera, *prim.bounding_sphere())
        if rect is None:
            t, face = prim.intersect(origin, dirs)
            closer = t < best_t
            best_t[closer], best_prim[closer], best_face[closer] = t[closer], i, face[closer]
            continue
        x0, x1, y0, y1 = rect
        idx = np.flatnonzero((px >= x0 - 1) & (px <= x1 + 1) & (py >= y0 - 1) & (py <= y1 + 1))
        if len(idx) == 0:
            continue
        t, face = prim.intersect(origin, dirs[:, idx])
        closer = t < best_t[idx]
        j = idx[closer]
        best_t[j], best_prim[j], best_face[j] = t[closer], i, face[closer]

    hit = best_prim >= 0
    depth = np.where(hit, best_t, 0.0)
    points = np.full((n, 3), np.nan) if geometry else np.empty((0, 3))
    normals = np.zeros((n, 3)) if geometry else np.empty((0, 3))
    color = np.empty((n, 3), dtype=np.float32)
    color[:] = np.asarray(scene.background, dtype=np.float32)
    light = scene.lighting
    l_dir = np.zeros(3) if light is None else np.asarray(light.direction, dtype=np.float64)
    l_dir = l_dir / max(float(np.linalg.norm(l_dir)), 1e-300)
    order = np.argsort(best_prim, kind="stable")
    bounds = np.searchsorted(best_prim[order], np.arange(-1, len(scene.primitives) + 1))
    for i, prim in enumerate(scene.primitives):
        sel = order[bounds[i + 1] : bounds[i + 2]]
        if len(sel) == 0:
            continue
        d = dirs[:, sel]
        p = origin[:, None] + best_t[sel] * d
        nrm, albedo = prim.surface(p, best_face[sel])
        if light is not None:
            shade = light.ambient + light.diffuse * np.maximum(_dot(l_dir, nrm), 0.0)
            albedo = albedo * shade[:, None].astype(np.float32)
        color[sel] = albedo
        if geometry:
            flip = np.where(nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2] > 0, -1.0, 1.0)  # face the camera
            normals[sel] = (nrm * flip).T
            points[sel] = p.T
    np.clip(color, 0.0, 1.0, out=color)
    return RayHits(depth=depth, points=points, normals=normals, color=color, primitive=best_prim)


@dataclass
class SyntheticView:
    """One rendered view with exact ground truth.

    Attributes:
        image: RGB in [0, 1], anti-aliased. [H, W, 3] float32
        depth: camera-space z of the first hit at each pixel centre, 0 where nothing is
            hit. [H, W] float32
        normals: world unit normals facing the camera at each pixel centre (0 where
            nothing is hit). [H, W, 3] float32
        camera: the camera.
    """

    image: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    camera: Camera

    @property
    def mask(self) -> np.ndarray:
        """Pixels whose centre ray hits a surface. [H, W] bool"""
        return self.depth > 0


def _pixel_grid(width: int, height: int, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """``x``, ``y`` of ``ss × ss`` samples in every pixel, row-major over ``[H·ss, W·ss]``. [H·ss·W·ss] each"""
    xs = (np.arange(width * ss) + 0.5) / ss
    ys = (np.arange(height * ss) + 0.5) / ss
    return np.tile(xs, height * ss), np.repeat(ys, width * ss)


def render(scene: Scene, camera: Camera, *, supersample: int = 2) -> SyntheticView:
    """Render a view of ``scene`` with its exact depth and normals.

    The colour of a pixel is the mean of ``supersample²`` samples on a regular grid
    inside it; depth and normals are those of the ray through the pixel centre.

    Args:
        scene: the scene.
        camera: the camera.
        supersample: samples per pixel along each axis (≥ 1).

    Returns:
        The view; ``image`` [H, W, 3], ``depth`` [H, W], ``normals`` [H, W, 3].
    """
    ss = int(supersample)
    if ss < 1:
        raise InputError(f"supersample must be a positive integer, got {supersample!r}")
    W, H = camera.width, camera.height
    centre = _cast(scene, camera, *_pixel_grid(W, H, 1), True)
    if ss == 1:
        image = centre.color.reshape(H, W, 3)
    else:
        samples = _cast(scene, camera, *_pixel_grid(W, H, ss), False)
        image = samples.color.reshape(H, ss, W, ss, 3).mean(axis=(1, 3))
    return SyntheticView(
        image=np.ascontiguousarray(image, dtype=np.float32),
        depth=centre.depth.reshape(H, W).astype(np.float32),
        normals=centre.normals.reshape(H, W, 3).astype(np.float32),
        camera=camera,
    )


def transfer_points(
    scene: Scene, cam0: Camera, cam1: Camera, pixels0: np.ndarray, *, rel_tol: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Exact correspondences: where the surface points seen at ``pixels0`` in ``cam0`` appear in ``cam1``.

    Args:
        scene: the scene.
        cam0: the first camera.
        cam1: the second camera.
        pixels0: ``(x, y)`` coordinates in ``cam0`` (pixel centres at +0.5). [N, 2]
        rel_tol: relative depth tolerance of the visibility test.

    Returns:
        ``(pixels1, visible)``: ``(x, y)`` coordinates in ``cam1`` (NaN where the ray
        of ``cam0`` hits nothing or the point is behind ``cam1``) [N, 2], and whether
        the point is inside ``cam1``'s image and not occluded there [N] bool.
    """
    hits0 = cast_rays(scene, cam0, pixels0)
    X = hits0.points
    Xc = X @ cam1.R.T + cam1.t
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = Xc @ cam1.K.T
        pix1 = proj[:, :2] / proj[:, 2:]
    front = np.isfinite(pix1).all(1) & (Xc[:, 2] > _EPS_T)
    pix1[~front] = np.nan
    inside = front & (pix1[:, 0] >= 0) & (pix1[:, 0] <= cam1.width) & (pix1[:, 1] >= 0) & (pix1[:, 1] <= cam1.height)
    visible = np.zeros(len(pix1), dtype=bool)
    idx = np.flatnonzero(inside)
    if len(idx):
        hits1 = cast_rays(scene, cam1, pix1[idx])
        visible[idx] = np.abs(hits1.depth - Xc[idx, 2]) <= rel_tol * Xc[idx, 2]
    return pix1, visible
