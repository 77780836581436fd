"""Textured synthetic scenes with exact ground truth, for tests and evaluation.

A small analytic ray caster (vectorised NumPy) renders scenes made of textured
rectangles (:class:`Quad`), oriented boxes (:class:`Box`) and spheres
(:class:`Sphere`) through a pinhole :class:`~macsplat_cli.cameras.Camera`, and
returns the image with its exact depth and normals (:func:`render`). Camera
pairs with a known baseline (:func:`orbit_pair`, :func:`forward_pair`,
:func:`pure_rotation_pair`) and the ground-truth relative pose
(:func:`relative_pose`, :func:`pose_errors`) make two-view reconstruction
measurable; :func:`transfer_points` gives exact correspondences and
:func:`write_dataset` writes a dataset folder.

**World.** OpenCV-style: y points *down* (floors are at larger y than
ceilings), units are metres.

**Textures.** Every primitive surface has 2D surface coordinates ``(u, v)`` in
metres; its texture is a function of ``(u, v)`` only, so it is fixed on the
surface and identical in every view. A textured surface is its ``albedo`` plus
several octaves of coloured value noise and a few thousand random discs, rings,
rectangles, triangles and lines per square metre (at ``scale = 1``),
deterministic from the texture's seed; ``textured=False`` gives flat colours.
Textures are rasterised once per surface (a few millimetres per texel, at most
:data:`MAX_TEXTURE_SIZE` texels a side), cached on the primitive, and sampled
bilinearly.

**Shading.** Lambertian with one directional light plus ambient,
``albedo · (ambient + diffuse · max(0, n·l))``, with ``n`` the primitive's own
(outward, or front for a quad) normal: independent of the viewpoint, so a
surface point has the same colour in every view (photo-consistency is exact up
to anti-aliasing).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from .cameras import Camera, CameraSet, save_cameras
from .errors import InputError, OutputPathError
from .images import save_depth, save_image

__all__ = [
    "MAX_TEXTURE_SIZE",
    "Box",
    "Lighting",
    "Primitive",
    "Quad",
    "RayHits",
    "Scene",
    "SceneKind",
    "Sphere",
    "SyntheticView",
    "Texture",
    "cast_rays",
    "forward_pair",
    "intrinsics",
    "look_at_camera",
    "make_scene",
    "object_scene",
    "orbit_cameras",
    "orbit_pair",
    "pose_errors",
    "pure_rotation_pair",
    "relative_pose",
    "render",
    "room_scene",
    "rotation_about",
    "transfer_points",
    "write_dataset",
]

SceneKind = Literal["room", "object"]
MAX_TEXTURE_SIZE = 1024
"""Largest side of a rasterised surface texture, in texels."""
_TEXEL = 0.004
"""Texel size in metres of a ``scale = 1`` texture (larger for surfaces over 4 m)."""
_EPS_T = 1e-6
"""Smallest accepted ray parameter (hits closer than this to the camera are ignored)."""
_COARSE_NOISE = ((0.64, 0.16), (0.32, 0.12), (0.16, 0.09), (0.08, 0.07))
"""(cell size in metres at scale 1, amplitude) of the noise octaves under the shapes."""
_FINE_NOISE = ((0.04, 0.05), (0.02, 0.04))
"""(cell size, amplitude) of the noise octaves over the shapes."""
_SHAPE_SPACING = 0.1
"""One random shape per ``(spacing · scale)²`` square metres."""
_SHAPE_RADIUS = (0.012, 0.12)
"""Range of shape radii in metres at scale 1 (log-uniform)."""
_MAX_SHAPES = 8000


# ------------------------------------------------------------------------------------ textures
@dataclass(frozen=True)
class Texture:
    """A procedural surface texture, a function of the surface coordinates ``(u, v)`` in metres.

    Attributes:
        albedo: base RGB colour in [0, 1].
        seed: seed of the random pattern (with the surface's face index).
        textured: ``False`` for a flat ``albedo`` (no pattern).
        scale: size of the pattern features relative to the default (noise cells of
            2 cm to 64 cm, shapes of 1.2 cm to 12 cm radius, 4 mm texels at ``scale = 1``).
    """

    albedo: tuple[float, float, float] = (0.6, 0.6, 0.6)
    seed: int = 0
    textured: bool = True
    scale: float = 1.0


def _draw_shapes(
    canvas: np.ndarray, rng: np.random.Generator, albedo: np.ndarray, area_m2: float, scale: float, texel: float
) -> None:
    """Draw random discs, rings, rectangles, triangles and line segments on an 8-bit RGB canvas, anti-aliased."""
    h, w = canvas.shape[:2]
    n = min(_MAX_SHAPES, int(area_m2 / (_SHAPE_SPACING * scale) ** 2))
    log_r = np.log(np.asarray(_SHAPE_RADIUS) * scale / texel)
    kinds = rng.integers(0, 5, n).tolist()
    xs, ys = rng.uniform(0.0, w, n), rng.uniform(0.0, h, n)
    rs = np.exp(rng.uniform(log_r[0], log_r[1], n))
    colors = (
        np.clip(np.rint((albedo * 0.25 + rng.uniform(0.02, 0.98, (n, 3)) * 0.75) * 255), 0, 255).astype(int).tolist()
    )
    angles = rng.uniform(0.0, 2.0 * np.pi, n)
    p1, p2 = rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n)
    tri = angles[:, None] + np.array([0.0, 2.1, 4.2]) + rng.uniform(-0.5, 0.5, (n, 3))
    sub = 16.0  # cv2 drawing with shift=4: coordinates in 1/16 texel
    cx, cy, rr = (xs * sub).astype(int).tolist(), (ys * sub).astype(int).tolist(), (rs * sub).astype(int).tolist()
    aa = cv2.LINE_AA
    for i, kind in enumerate(kinds):
        color, r = tuple(colors[i]), float(rs[i])
        if kind == 0:  # disc
            cv2.circle(canvas, (cx[i], cy[i]), rr[i], color, -1, aa, 4)
        elif kind == 1:  # ring
            cv2.circle(canvas, (cx[i], cy[i]), rr[i], color, max(1, round(r * (0.15 + 0.25 * p1[i]))), aa, 4)
        elif kind == 2:  # rotated rectangle
            size = (2 * r * (0.4 + 0.6 * p1[i]), 2 * r * (0.4 + 0.6 * p2[i]))
            pts = cv2.boxPoints(((float(xs[i]), float(ys[i])), size, float(np.degrees(angles[i]))))
            cv2.fillPoly(canvas, [np.rint(pts * sub).astype(np.int32)], color, aa, 4)
        elif kind == 3:  # triangle
            pts = np.stack([xs[i] + r * np.cos(tri[i]), ys[i] + r * np.sin(tri[i])], -1)
            cv2.fillPoly(canvas, [np.rint(pts * sub).astype(np.int32)], color, aa, 4)
        else:  # line segment
            dx, dy = 2.0 * r * math.cos(angles[i]) * sub, 2.0 * r * math.sin(angles[i]) * sub
            q0 = (int(cx[i] - dx), int(cy[i] - dy))
            q1 = (int(cx[i] + dx), int(cy[i] + dy))
            cv2.line(canvas, q0, q1, color, max(1, round(r * (0.1 + 0.2 * p1[i]))), aa, 4)


def _texture_image(tex: Texture, width_m: float, height_m: float, key: int) -> tuple[np.ndarray, float]:
    """Rasterise ``tex`` over ``[0, width_m] × [0, height_m]`` metres.

    Returns:
        ``(image, texel)``: float32 RGB ``[h, w, 3]`` whose texel ``(i, j)`` covers
        ``[j·texel, (j+1)·texel] × [i·texel, (i+1)·texel]``, and the texel size in metres.
    """
    s = float(tex.scale)
    texel = max(_TEXEL * s, max(width_m, height_m) / MAX_TEXTURE_SIZE)
    w = max(2, math.ceil(width_m / texel))
    h = max(2, math.ceil(height_m / texel))
    albedo = np.asarray(tex.albedo, dtype=np.float32)
    img = np.empty((h, w, 3), dtype=np.float32)
    img[:] = albedo
    rng = np.random.default_rng([int(tex.seed) & 0xFFFFFFFF, key])
    u = ((np.arange(w, dtype=np.float64) + 0.5) * texel).astype(np.float32)
    v = ((np.arange(h, dtype=np.float64) + 0.5) * texel).astype(np.float32)

    def add_noise(octaves: tuple[tuple[float, float], ...]) -> None:
        for cell_1, amp in octaves:
            cell = cell_1 * s
            if cell < 2.0 * texel:
                continue
            grid = rng.uniform(-1.0, 1.0, (math.ceil(height_m / cell) + 4, math.ceil(width_m / cell) + 4, 3))
            map_x = np.ascontiguousarray(np.broadcast_to(u[None, :] / cell + 1.0, (h, w)), dtype=np.float32)
            map_y = np.ascontiguousarray(np.broadcast_to(v[:, None] / cell + 1.0, (h, w)), dtype=np.float32)
            img[:] += amp * cv2.remap(
                grid.astype(np.float32), map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
            )

    add_noise(_COARSE_NOISE)
    canvas = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    _draw_shapes(canvas, rng, albedo, width_m * height_m, s, texel)
    img = canvas.astype(np.float32) / 255.0
    add_noise(_FINE_NOISE)
    np.clip(img, 0.0, 1.0, out=img)
    return img, texel


def _bilinear(img: np.ndarray, texel: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``img`` at surface coordinates in metres (clamped at the border). [M] → [M, 3]"""
    h, w = img.shape[:2]
    x = np.clip(u * (1.0 / texel) - 0.5, 0.0, w - 1.0)
    y = np.clip(v * (1.0 / texel) - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.intp), w - 2)
    y0 = np.minimum(y.astype(np.intp), h - 2)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    flat = img.reshape(-1, 3)
    i00 = y0 * w + x0
    c00, c01, c10, c11 = flat[i00], flat[i00 + 1], flat[i00 + w], flat[i00 + w + 1]
    top = c00 + (c01 - c00) * fx
    bottom = c10 + (c11 - c10) * fx
    return top + (bottom - top) * fy


# ------------------------------------------------------------------------------------ primitives
# Rays and points are component-major ([3, N]): NumPy is several times faster on three
# contiguous rows than on [N, 3] (whose small matrix products take a slow path).
def _dot(v: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``v · d`` for a fixed vector and component-major vectors. [3], [3, N] → [N]"""
    return v[0] * d[0] + v[1] * d[1] + v[2] * d[2]


class Primitive:
    """Base class of the ray-castable primitives.

    Subclasses implement :meth:`intersect`, :meth:`surface` and :meth:`bounding_sphere`.
    Vectors are component-major: ``dirs`` and ``points`` are ``[3, N]``.
    """

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of each ray ``origin + t · dirs`` with ``t > 1e-6``.

        Args:
            origin: common ray origin. [3]
            dirs: ray directions (any non-zero length), component-major. [3, N]

        Returns:
            ``(t, face)``: ray parameter (``inf`` where the ray misses) [N], and the
            index of the face hit (0 for single-face primitives) [N] int8.
        """
        raise NotImplementedError

    def surface(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Geometric normal and texture colour at surface points.

        Args:
            points: points on the surface, component-major. [3, M]
            face: face index of each point, from :meth:`intersect`. [M]

        Returns:
            ``(normals, albedo)``: outward (front for a quad) unit normals, component-major
            [3, M], and unshaded RGB colours in [0, 1] [M, 3] float32.
        """
        raise NotImplementedError

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre [3] and radius of a sphere containing the primitive."""
        raise NotImplementedError


def _vec3(x: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InputError(f"{what} must be 3 finite numbers, got {x!r}")
    return a


def _rotation(R: Sequence[Sequence[float]] | np.ndarray | None) -> np.ndarray:
    if R is None:
        return np.eye(3)
    a = np.asarray(R, dtype=np.float64)
    if a.shape != (3, 3) or np.abs(a.T @ a - np.eye(3)).max() > 1e-6 or np.linalg.det(a) < 0:
        raise InputError("rotation must be a proper 3x3 rotation matrix")
    return a


def _sample(
    tex: Texture, cache: dict, key: int, width_m: float, height_m: float, u: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """Texture colour at ``(u, v)`` metres on a ``width_m × height_m`` surface (rasterised once, cached). [M, 3]"""
    if not tex.textured:
        return np.broadcast_to(np.asarray(tex.albedo, dtype=np.float32), (len(u), 3))
    if ("tex", key) not in cache:
        cache[("tex", key)] = _texture_image(tex, width_m, height_m, key)
    img, texel = cache[("tex", key)]
    return _bilinear(img, texel, u, v)


@dataclass(frozen=True, eq=False)
class Quad(Primitive):
    """A parallelogram (usually a rectangle) ``origin + a·edge_u + b·edge_v``, ``a, b ∈ [0, 1]``.

    Surface coordinates are ``(a·|edge_u|, b·|edge_v|)`` metres; the front normal is
    ``edge_u × edge_v`` normalised (it only matters for shading). Visible from both sides.

    Attributes:
        origin: one corner. [3]
        edge_u: first edge from ``origin``. [3]
        edge_v: second edge from ``origin``. [3]
        texture: the surface texture.
    """

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: Texture = field(default_factory=Texture)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", _vec3(self.origin, "origin"))
        object.__setattr__(self, "edge_u", _vec3(self.edge_u, "edge_u"))
        object.__setattr__(self, "edge_v", _vec3(self.edge_v, "edge_v"))
        eu, ev = self.edge_u, self.edge_v
        n = np.cross(eu, ev)
        if np.linalg.norm(n) < 1e-12:
            raise InputError("quad edges must be non-zero and not parallel")
        gram = np.array([[eu @ eu, eu @ ev], [eu @ ev, ev @ ev]])
        # rows du, dv: the dual basis in the plane (du·eu = 1, du·ev = 0, dv·eu = 0, dv·ev = 1)
        self._cache["dual"] = np.linalg.inv(gram) @ np.stack([eu, ev])
        self._cache["normal"] = n / np.linalg.norm(n)

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n, (du, dv) = self._cache["normal"], self._cache["dual"]
        rel = origin - self.origin
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -float(rel @ n) / _dot(n, dirs)
            a = float(rel @ du) + t * _dot(du, dirs)
            b = float(rel @ dv) + t * _dot(dv, dirs)
            ok = (t > _EPS_T) & (a >= 0.0) & (a <= 1.0) & (b >= 0.0) & (b <= 1.0)
        return np.where(ok, t, np.inf), np.zeros(len(t), dtype=np.int8)

    def surface(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        du, dv = self._cache["dual"]
        rel = points - self.origin[:, None]
        lu, lv = float(np.linalg.norm(self.edge_u)), float(np.linalg.norm(self.edge_v))
        u, v = _dot(du, rel) * lu, _dot(dv, rel) * lv
        normals = np.repeat(self._cache["normal"][:, None], points.shape[1], axis=1)
        return normals, _sample(self.texture, self._cache, 0, lu, lv, u, v)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        centre = self.origin + 0.5 * (self.edge_u + self.edge_v)
        radius = 0.5 * max(np.linalg.norm(self.edge_u + self.edge_v), np.linalg.norm(self.edge_u - self.edge_v))
        return centre, float(radius)


@dataclass(frozen=True, eq=False)
class Box(Primitive):
    """An oriented box, visible from outside and from inside.

    Face ``2k + s`` is the face of local axis ``k`` on the negative (``s = 0``) or positive
    (``s = 1``) side; each face has its own texture pattern (seeded by the face index),
    with surface coordinates the two other local coordinates shifted to ``[0, 2·half]``.

    Attributes:
        center: box centre. [3]
        half_size: half extents along the local axes. [3]
        rotation: world-from-box rotation; its columns are the box axes (``None``:
            axis-aligned). [3, 3]
        texture: the texture of all six faces (different patterns, same style).
    """

    center: np.ndarray
    half_size: np.ndarray
    rotation: np.ndarray | None = None
    texture: Texture = field(default_factory=Texture)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        object.__setattr__(self, "half_size", _vec3(self.half_size, "half_size"))
        object.__setattr__(self, "rotation", _rotation(self.rotation))
        if (self.half_size <= 0).any():
            raise InputError(f"box half sizes must be positive, got {self.half_size.tolist()}")

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, h = self.rotation, self.half_size
        o = (origin - self.center) @ R  # local origin [3]
        d = [_dot(R[:, k], dirs) for k in range(3)]  # local directions, per axis [N]
        tmin, tmax = [], []
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                inv = 1.0 / d[k]
                t1 = (-h[k] - o[k]) * inv
                t2 = (h[k] - o[k]) * inv
                tmin.append(np.minimum(t1, t2))
                tmax.append(np.maximum(t1, t2))
        t_near = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
        t_far = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        hit = (t_near <= t_far) & (t_far > _EPS_T)
        outside = t_near > _EPS_T
        t = np.where(hit, np.where(outside, t_near, t_far), np.inf)
        # axis of the face hit: the slab that sets t_near (entering) or t_far (leaving, from inside)
        k_near = np.where(tmin[0] == t_near, 0, np.where(tmin[1] == t_near, 1, 2))
        k_far = np.where(tmax[0] == t_far, 0, np.where(tmax[1] == t_far, 1, 2))
        k = np.where(outside, k_near, k_far)
        d_k = np.choose(k, d)
        # entering through the face turned towards the ray (the − face when d_k > 0); leaving through the other
        positive = np.where(outside, d_k < 0, d_k > 0)
        return t, (2 * k + positive).astype(np.int8)

    def surface(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, h = self.rotation, self.half_size
        rel = points - self.center[:, None]
        q = [_dot(R[:, k], rel) for k in range(3)]  # local coordinates
        k = face // 2
        sign = np.where(face % 2 == 1, 1.0, -1.0)
        normals = R[:, k] * sign  # [3, M]
        albedo = np.empty((points.shape[1], 3), dtype=np.float32)
        for f in np.unique(face):
            sel = face == f
            a, b = (int(f) // 2 + 1) % 3, (int(f) // 2 + 2) % 3
            u, v = q[a][sel] + h[a], q[b][sel] + h[b]
            albedo[sel] = _sample(self.texture, self._cache, int(f), 2 * h[a], 2 * h[b], u, v)
        return normals, albedo

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.center.copy(), float(np.linalg.norm(self.half_size))


@dataclass(frozen=True, eq=False)
class Sphere(Primitive):
    """A sphere, visible from outside and from inside, textured in a sinusoidal (equal-area) projection.

    Surface coordinates: ``u = r·φ·sin θ + π r``, ``v = r·θ`` with ``θ`` the polar angle
    from the local +y axis and ``φ`` the azimuth, in metres; the seam (``φ = ±π``) and
    the poles follow ``rotation``.

    Attributes:
        center: centre. [3]
        radius: radius in metres.
        rotation: world-from-sphere rotation of the texture frame (``None``: identity). [3, 3]
        texture: the surface texture.
    """

    center: np.ndarray
    radius: float
    rotation: np.ndarray | None = None
    texture: Texture = field(default_factory=Texture)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        object.__setattr__(self, "rotation", _rotation(self.rotation))
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise InputError(f"sphere radius must be positive, got {self.radius!r}")
        object.__setattr__(self, "radius", float(self.radius))

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        oc = origin - self.center
        a = dirs[0] * dirs[0] + dirs[1] * dirs[1] + dirs[2] * dirs[2]
        b = _dot(oc, dirs)
        c = float(oc @ oc) - self.radius**2
        disc = b * b - a * c
        with np.errstate(invalid="ignore"):
            root = np.sqrt(disc)
            t0 = (-b - root) / a
            t1 = (-b + root) / a
        t = np.where(t0 > _EPS_T, t0, np.where(t1 > _EPS_T, t1, np.inf))  # NaN (no real root) → inf
        return t, np.zeros(len(t), dtype=np.int8)

    def surface(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = self.radius
        normals = points - self.center[:, None]
        normals /= np.sqrt(_dot(normals, normals))
        q = [_dot(self.rotation[:, k], normals) for k in range(3)]  # texture-frame directions
        theta = np.arccos(np.clip(q[1], -1.0, 1.0))
        phi = np.arctan2(q[0], q[2])
        u = r * phi * np.sin(theta) + math.pi * r
        v = r * theta
        return normals, _sample(self.texture, self._cache, 0, 2 * math.pi * r, math.pi * r, u, v)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.center.copy(), self.radius


# ------------------------------------------------------------------------------------ scenes
@dataclass(frozen=True)
class Lighting:
    """View-independent Lambertian lighting: ``albedo · (ambient + diffuse · max(0, n·l))``.

    Attributes:
        direction: direction *towards* the light in world coordinates (normalised on
            use); the default comes from above (−y), slightly from the side. [3]
        ambient: ambient term.
        diffuse: weight of the directional term.
    """

    direction: tuple[float, float, float] = (0.35, -1.0, -0.55)
    ambient: float = 0.45
    diffuse: float = 0.6


@dataclass(eq=False)
class Scene:
    """Primitives, lighting, and the viewpoint the camera builders aim at.

    Attributes:
        primitives: the surfaces.
        lighting: the light (``None``: unshaded, colour = albedo).
        background: colour of rays that hit nothing (RGB in [0, 1]).
        target: the point cameras look at (the scene or object centre). [3]
        view_distance: distance of orbit cameras from ``target`` in metres.
        view_elevation_deg: elevation of orbit cameras above ``target`` (degrees).
        name: a label.
    """

    primitives: list[Primitive]
    lighting: Lighting | None = field(default_factory=Lighting)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    view_distance: float = 3.0
    view_elevation_deg: float = 15.0
    name: str = "scene"

    def __post_init__(self) -> None:
        self.target = _vec3(self.target, "target")


def _random_texture(
    rng: np.random.Generator, textured: bool, scale: float, lo: float = 0.25, hi: float = 0.8
) -> Texture:
    albedo = tuple(float(c) for c in rng.uniform(lo, hi, 3))
    return Texture(albedo=albedo, seed=int(rng.integers(0, 2**31)), textured=textured, scale=scale)  # type: ignore[arg-type]


def _inside_box_quads(lo: np.ndarray, hi: np.ndarray, textures: Sequence[Texture]) -> list[Primitive]:
    """Six quads bounding the box ``[lo, hi]`` with front normals pointing inwards.

    Order: floor (+y), ceiling (−y), walls −x, +x, −z, +z.
    """
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    dx, dy, dz = hi - lo
    ex, ey, ez = np.eye(3)
    quads = [
        Quad((x0, y1, z0), dx * ex, dz * ez, textures[0]),  # floor: normal −y (up)
        Quad((x0, y0, z0), dz * ez, dx * ex, textures[1]),  # ceiling: normal +y
        Quad((x0, y0, z0), dy * ey, dz * ez, textures[2]),  # wall x0: normal +x
        Quad((x1, y0, z0), dz * ez, dy * ey, textures[3]),  # wall x1: normal −x
        Quad((x0, y0, z0), dx * ex, dy * ey, textures[4]),  # wall z0: normal +z
        Quad((x0, y0, z1), dy * ey, dx * ex, textures[5]),  # wall z1: normal −z
    ]
    return quads


def rotation_about(axis: Sequence[float] | np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation matrix of ``angle_deg`` degrees about ``axis`` (right-handed, Rodrigues). [3, 3]"""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    th = math.radians(angle_deg)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * (Kx @ Kx)


# Camera layouts of the built-in scenes: (target, view distance, elevation in degrees).
_ROOM_HALF = np.array([3.0, 1.5, 3.0])
_ROOM_LAYOUT = (np.array([0.0, 0.6, 0.0]), 2.4, 15.0)
_OBJECT_LAYOUT = (np.array([0.0, -0.2, 0.0]), 1.4, 25.0)


def room_scene(seed: int = 0, *, textured: bool = True) -> Scene:
    """The inside of a 6 × 3 × 6 m textured room with boxes and spheres on the floor.

    World: the room spans ``x, z ∈ [−3, 3]``, ``y ∈ [−1.5, 1.5]`` with the floor at
    ``y = +1.5``. Five boxes (0.3–1 m) stand on the floor at different distances from
    the centre (0.5 to 2.4 m), the nearest one with a sphere on top, and two more
    spheres lie on the floor. Away from the centre nothing is higher than 1 m, so the
    cameras of :func:`orbit_pair` and :func:`forward_pair` (about 1.4 m above the floor,
    2.2–2.5 m from the centre) never lie inside an object.

    Args:
        seed: seed of the layout, colours and textures.
        textured: ``False`` gives flat colours (for textureless failure tests).
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 1])
    floor_y = float(_ROOM_HALF[1])
    prims: list[Primitive] = _inside_box_quads(
        -_ROOM_HALF, _ROOM_HALF, [_random_texture(rng, textured, 1.0) for _ in range(6)]
    )
    radii = [0.5, 0.9, 1.6, 2.0, 2.4]  # distances from the centre: objects at different depths
    start = rng.uniform(0, 2 * np.pi)
    tops = []
    for i, rad in enumerate(radii):
        ang = start + i * 2 * np.pi / len(radii) + rng.uniform(-0.3, 0.3)
        half = np.array([rng.uniform(0.15, 0.45), rng.uniform(0.15, 0.5), rng.uniform(0.15, 0.45)])
        centre = np.array([rad * math.cos(ang), floor_y - half[1], rad * math.sin(ang)])
        centre[[0, 2]] = np.clip(centre[[0, 2]], -2.95 + half.max(), 2.95 - half.max())
        rot = rotation_about((0, 1, 0), float(rng.uniform(0, 90)))
        prims.append(Box(centre, half, rot, _random_texture(rng, textured, 0.6, 0.2, 0.9)))
        tops.append((centre, half))
    # a sphere on top of the first box, and two on the floor
    c, h = tops[0]
    r = float(rng.uniform(0.15, min(0.3, h[0], h[2]) + 0.05))
    prims.append(
        Sphere(
            c - np.array([0, h[1] + r, 0]),
            r,
            rotation_about(rng.normal(size=3), float(rng.uniform(0, 360))),
            _random_texture(rng, textured, 0.4, 0.2, 0.9),
        )
    )
    for rad in (1.2, 2.1):
        ang = rng.uniform(0, 2 * np.pi)
        r = float(rng.uniform(0.2, 0.4))
        centre = np.array([rad * math.cos(ang), floor_y - r, rad * math.sin(ang)])
        prims.append(
            Sphere(
                centre,
                r,
                rotation_about(rng.normal(size=3), float(rng.uniform(0, 360))),
                _random_texture(rng, textured, 0.4, 0.2, 0.9),
            )
        )
    target, dist, elev = _ROOM_LAYOUT
    return Scene(prims, target=target.copy(), view_distance=dist, view_elevation_deg=elev, name=f"room-{seed}")


def object_scene(seed: int = 0, *, textured: bool = True) -> Scene:
    """An object of about 0.5 m on a textured table, inside a large textured backdrop room.

    World: the table top is the plane ``y = 0`` (``2 × 1.4`` m, on four legs); the
    object (a box with a sphere on top, a small box and a small sphere beside it) is
    centred on the origin and rises to ``y ≈ −0.55``; the backdrop room spans
    ``x, z ∈ [−5, 5]``, ``y ∈ [−4, 0.9]`` (floor at ``y = 0.9``).

    Args:
        seed: seed of the layout, colours and textures.
        textured: ``False`` gives flat colours.
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 2])
    prims: list[Primitive] = _inside_box_quads(
        np.array([-5.0, -4.0, -5.0]), np.array([5.0, 0.9, 5.0]), [_random_texture(rng, textured, 1.5) for _ in range(6)]
    )
    table_tex = _random_texture(rng, textured, 0.5, 0.3, 0.7)
    prims.append(Box((0.0, 0.03, 0.0), (1.0, 0.03, 0.7), None, table_tex))
    for sx in (-1, 1):
        for sz in (-1, 1):
            prims.append(Box((sx * 0.9, 0.48, sz * 0.6), (0.04, 0.42, 0.04), None, table_tex))
    yaw = rotation_about((0, 1, 0), float(rng.uniform(-25, 25)))
    main_half = np.array([0.16, 0.15, 0.13]) * rng.uniform(0.9, 1.1, 3)
    prims.append(Box((0.0, -main_half[1], 0.0), main_half, yaw, _random_texture(rng, textured, 0.25, 0.2, 0.9)))
    r = 0.12 * float(rng.uniform(0.9, 1.1))
    spin = rotation_about(rng.normal(size=3), float(rng.uniform(0, 360)))
    prims.append(Sphere((0.0, -2 * main_half[1] - r, 0.0), r, spin, _random_texture(rng, textured, 0.25, 0.2, 0.9)))
    small = 0.07
    yaw2 = rotation_about((0, 1, 0), float(rng.uniform(0, 90)))
    prims.append(Box((0.3, -small, 0.12), (small, small, small), yaw2, _random_texture(rng, textured, 0.25, 0.2, 0.9)))
    r2 = 0.06
    spin2 = rotation_about(rng.normal(size=3), float(rng.uniform(0, 360)))
    prims.append(Sphere((-0.27, -r2, -0.12), r2, spin2, _random_texture(rng, textured, 0.25, 0.2, 0.9)))
    target, dist, elev = _OBJECT_LAYOUT
    return Scene(prims, target=target.copy(), view_distance=dist, view_elevation_deg=elev, name=f"object-{seed}")


def make_scene(kind: SceneKind, seed: int = 0, *, textured: bool = True) -> Scene:
    """:func:`room_scene` or :func:`object_scene` by name."""
    if kind == "room":
        return room_scene(seed, textured=textured)
    if kind == "object":
        return object_scene(seed, textured=textured)
    raise InputError(f"unknown synthetic scene kind {kind!r}; use 'room' or 'object'")


# ------------------------------------------------------------------------------------ ray casting
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


# ------------------------------------------------------------------------------------ cameras
def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Centred pinhole ``K`` (``cx = W/2``, ``cy = H/2``, square pixels) of horizontal field of view ``fov_deg``.

    Returns:
        ``K``. [3, 3]
    """
    if not 0 < fov_deg < 180:
        raise InputError(f"field of view must be in (0, 180) degrees, got {fov_deg!r}")
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def _look_at(eye: np.ndarray, target: np.ndarray, roll_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenCV axes) of a camera at ``eye`` looking at ``target``, image-down ≈ world +y."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    if np.linalg.norm(x) < 1e-9:  # looking straight up or down
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1) @ rotation_about((0, 0, 1), roll_deg)
    T[:3, 3] = eye
    return T


def look_at_camera(
    name: str,
    eye: Sequence[float] | np.ndarray,
    target: Sequence[float] | np.ndarray,
    *,
    width: int = 512,
    height: int = 384,
    fov_deg: float = 60.0,
    roll_deg: float = 0.0,
) -> Camera:
    """A camera at ``eye`` looking at ``target`` with world +y down in the image, rolled by ``roll_deg``.

    Args:
        name: camera name.
        eye: camera centre. [3]
        target: point on the optical axis. [3]
        width: image width in pixels.
        height: image height in pixels.
        fov_deg: horizontal field of view.
        roll_deg: rotation about the optical axis (positive: clockwise in the image).
    """
    eye_, target_ = _vec3(eye, "eye"), _vec3(target, "target")
    return Camera(name, width, height, intrinsics(width, height, fov_deg), _look_at(eye_, target_, roll_deg))


def _scene_layout(scene: SceneKind | Scene) -> tuple[np.ndarray, float, float]:
    if isinstance(scene, Scene):
        return scene.target.copy(), float(scene.view_distance), float(scene.view_elevation_deg)
    if scene == "room":
        target, dist, elev = _ROOM_LAYOUT
    elif scene == "object":
        target, dist, elev = _OBJECT_LAYOUT
    else:
        raise InputError(f"unknown synthetic scene kind {scene!r}; use 'room' or 'object'")
    return target.copy(), dist, elev


def _orbit_eye(target: np.ndarray, dist: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Point at ``dist`` from ``target`` at the given azimuth (0: on the −z side) and elevation (above: −y)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return target + dist * np.array([-math.sin(az) * math.cos(el), -math.sin(el), -math.cos(az) * math.cos(el)])


def orbit_cameras(
    scene: SceneKind | Scene,
    azimuths_deg: Sequence[float],
    *,
    elevation_deg: float | None = None,
    distance: float | None = None,
    width: int = 512,
    height: int = 384,
    fov_deg: float = 60.0,
    names: Sequence[str] | None = None,
) -> list[Camera]:
    """Cameras on a circle around the scene's target, all looking at it (no jitter).

    Args:
        scene: a scene kind (``"room"``/``"object"``) or a :class:`Scene` (its
            ``target``, ``view_distance``, ``view_elevation_deg``).
        azimuths_deg: azimuth of each camera about the vertical axis through the target
            (0: on the −z side, looking towards +z).
        elevation_deg: elevation above the target (default: the scene's).
        distance: distance to the target (default: the scene's).
        width: image width.
        height: image height.
        fov_deg: horizontal field of view.
        names: camera names (default ``view0``, ``view1``, …).
    """
    target, dist, elev = _scene_layout(scene)
    dist = dist if distance is None else float(distance)
    elev = elev if elevation_deg is None else float(elevation_deg)
    names = list(names) if names is not None else [f"view{i}" for i in range(len(azimuths_deg))]
    if len(names) != len(azimuths_deg):
        raise InputError(f"got {len(names)} names for {len(azimuths_deg)} cameras")
    return [
        look_at_camera(n, _orbit_eye(target, dist, a, elev), target, width=width, height=height, fov_deg=fov_deg)
        for n, a in zip(names, azimuths_deg)
    ]


def orbit_pair(
    scene: SceneKind | Scene,
    angle_deg: float,
    *,
    width: int = 512,
    height: int = 384,
    fov_deg: float = 60.0,
    seed: int = 0,
    jitter: bool = True,
    names: tuple[str, str] = ("view0", "view1"),
) -> tuple[Camera, Camera]:
    """Two cameras looking at the scene's target, ``angle_deg`` apart around the vertical axis.

    Both cameras look exactly at the target from about the scene's view distance and
    elevation; camera 1 is turned about the vertical axis through the target. With
    ``jitter``, a seeded random base azimuth (±20°), and small per-camera changes of
    elevation (±2°, limited to ``angle/2`` between the two), roll (±2°) and distance
    (±5%) make the pair generic; the azimuth step is then adjusted so that **the angle
    between the two optical axes is exactly** ``angle_deg`` (it is the angle subtended
    at the target by the two camera centres).

    Args:
        scene: ``"room"``, ``"object"`` or a :class:`Scene`.
        angle_deg: angle between the optical axes in degrees, in [0, 180 − 2·elevation).
        width: image width.
        height: image height.
        fov_deg: horizontal field of view.
        seed: seed of the jitter.
        jitter: ``False`` for the symmetric pair without jitter (azimuths ±angle/2).
        names: camera names.

    Returns:
        ``(camera0, camera1)``.
    """
    target, dist, elev = _scene_layout(scene)
    alpha = math.radians(float(angle_deg))
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 3])
    if jitter:
        base = float(rng.uniform(-20, 20))
        e0 = elev + float(rng.uniform(-2, 2))
        e1 = e0 + float(np.clip(rng.uniform(-2, 2), -0.5 * angle_deg, 0.5 * angle_deg))
        rolls = rng.uniform(-2, 2, 2)
        dists = dist * rng.uniform(0.95, 1.05, 2)
    else:
        base, e0, e1, rolls, dists = 0.0, elev, elev, np.zeros(2), np.full(2, dist)
    r0, r1 = math.radians(e0), math.radians(e1)
    # cos(angle) = cos e0 cos e1 cos Δ + sin e0 sin e1 → the azimuth step Δ
    cos_delta = (math.cos(alpha) - math.sin(r0) * math.sin(r1)) / (math.cos(r0) * math.cos(r1))
    if not -1.0 <= cos_delta <= 1.0 + 1e-12:
        raise InputError(f"orbit angle {angle_deg!r} is not reachable at elevation {elev:g}°")
    delta = math.degrees(math.acos(min(cos_delta, 1.0)))
    azimuths = (base - delta / 2, base + delta / 2)
    cams = tuple(
        look_at_camera(
            names[i],
            _orbit_eye(target, float(dists[i]), azimuths[i], (e0, e1)[i]),
            target,
            width=width,
            height=height,
            fov_deg=fov_deg,
            roll_deg=float(rolls[i]),
        )
        for i in range(2)
    )
    return cams[0], cams[1]


def forward_pair(
    scene: SceneKind | Scene,
    *,
    forward: float = 0.25,
    rotation_deg: float = 3.0,
    width: int = 512,
    height: int = 384,
    fov_deg: float = 60.0,
    seed: int = 0,
    names: tuple[str, str] = ("view0", "view1"),
) -> tuple[Camera, Camera]:
    """Camera 1 moved mostly forward along camera 0's optical axis, slightly rotated.

    Camera 0 is the first camera of the jittered :func:`orbit_pair` layout (looking at
    the target). Camera 1 moves by ``forward × distance to the target`` along the optical
    axis plus a sideways/vertical offset of at most 10% of that, and is rotated by
    exactly ``rotation_deg`` about a random axis. The epipole lies near the image centre:
    a hard case for essential-matrix estimation.

    Args:
        scene: ``"room"``, ``"object"`` or a :class:`Scene`.
        forward: forward motion as a fraction of the distance to the target (below about
            0.5, the camera stays clear of the objects of the built-in scenes).
        rotation_deg: rotation angle between the two cameras.
        width: image width.
        height: image height.
        fov_deg: horizontal field of view.
        seed: seed of the layout jitter.
        names: camera names.
    """
    cam0, _ = orbit_pair(scene, 0.0, width=width, height=height, fov_deg=fov_deg, seed=seed, names=names)
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 4])
    target, _, _ = _scene_layout(scene)
    move = forward * float(np.linalg.norm(target - cam0.center))
    c2w0 = cam0.cam_to_world
    offset_cam = np.array([*rng.uniform(-0.1, 0.1, 2) / math.sqrt(2), 1.0]) * move
    T = np.eye(4)
    T[:3, :3] = c2w0[:3, :3] @ rotation_about(rng.normal(size=3), rotation_deg)
    T[:3, 3] = c2w0[:3, 3] + c2w0[:3, :3] @ offset_cam
    return cam0, Camera(names[1], width, height, cam0.K, T)


def pure_rotation_pair(
    scene: SceneKind | Scene,
    angle_deg: float,
    *,
    width: int = 512,
    height: int = 384,
    fov_deg: float = 60.0,
    seed: int = 0,
    names: tuple[str, str] = ("view0", "view1"),
) -> tuple[Camera, Camera]:
    """Two cameras with the same centre (zero baseline), rotated by ``angle_deg``.

    Camera 0 is the first camera of the jittered :func:`orbit_pair` layout; camera 1
    turns by exactly ``angle_deg`` about an axis close to camera 0's vertical (y) axis
    (seeded tilt up to ~10°): a pan, for failure tests (no parallax, the essential
    matrix is undefined).
    """
    cam0, _ = orbit_pair(scene, 0.0, width=width, height=height, fov_deg=fov_deg, seed=seed, names=names)
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 5])
    axis = np.array([rng.uniform(-0.18, 0.18), 1.0, rng.uniform(-0.18, 0.18)])
    T = cam0.cam_to_world.copy()
    T[:3, :3] = T[:3, :3] @ rotation_about(axis, angle_deg)
    return cam0, Camera(names[1], width, height, cam0.K, T)


# ------------------------------------------------------------------------------------ poses
def relative_pose(cam0: Camera, cam1: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pose of camera 1 in camera 0's frame: ``X_cam1 = R · X_cam0 + t``.

    This is what an essential-matrix estimate recovers (``t`` up to scale, here in
    world units): ``E = [t]× R``.

    Returns:
        ``(R, t)``: rotation [3, 3] and translation [3].
    """
    T = cam1.world_to_cam @ cam0.cam_to_world
    return T[:3, :3].copy(), T[:3, 3].copy()


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b))))


def pose_errors(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray) -> tuple[float, float]:
    """Rotation error and translation-direction error between two relative poses, in degrees.

    Args:
        R_est: estimated rotation. [3, 3]
        t_est: estimated translation (any scale). [3]
        R_gt: true rotation. [3, 3]
        t_gt: true translation (any scale). [3]

    Returns:
        ``(rotation_error_deg, translation_error_deg)``: the angle of ``R_estᵀ R_gt`` in
        [0, 180], and the plain angle between ``t_est`` and ``t_gt`` in [0, 180] (a
        translation of the opposite sign is 180° off; NaN if either is zero).
    """
    D = np.asarray(R_est, dtype=np.float64).T @ np.asarray(R_gt, dtype=np.float64)
    sin = 0.5 * float(np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]))
    cos = 0.5 * (float(np.trace(D)) - 1.0)
    rot_err = math.degrees(math.atan2(sin, cos))
    a = np.asarray(t_est, dtype=np.float64).reshape(3)
    b = np.asarray(t_gt, dtype=np.float64).reshape(3)
    if np.linalg.norm(a) == 0 or np.linalg.norm(b) == 0:
        return rot_err, float("nan")
    return rot_err, _angle_between(a, b)


# ------------------------------------------------------------------------------------ datasets
def write_dataset(
    folder: str | os.PathLike[str],
    scene: Scene,
    cameras: Sequence[Camera],
    *,
    depth: bool = True,
    supersample: int = 2,
) -> list[SyntheticView]:
    """Render ``cameras`` and write a dataset folder.

    Layout: ``images/<name>.png`` (8-bit RGB), ``depth/<name>.png`` (16-bit, depth in
    millimetres, 0 = no hit; with ``depth``), and ``cameras.json``
    (:func:`~macsplat_cli.cameras.save_cameras`, ``scale="metric"``, ``world="world"``).

    Args:
        folder: output folder (created if missing).
        scene: the scene.
        cameras: the cameras (names unique; used as file stems).
        depth: also write depth maps.
        supersample: anti-aliasing of :func:`render`.

    Returns:
        The rendered views, in the order of ``cameras``.

    Raises:
        OutputPathError: the folder cannot be created or written.
    """
    root = Path(folder)
    camera_set = CameraSet(list(cameras), scale="metric", world="world")
    try:
        (root / "images").mkdir(parents=True, exist_ok=True)
        if depth:
            (root / "depth").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create {root}: {e.strerror or e}") from e
    views = []
    for cam in camera_set:
        view = render(scene, cam, supersample=supersample)
        save_image(root / "images" / f"{cam.name}.png", view.image)
        if depth:
            save_depth(root / "depth" / f"{cam.name}.png", view.depth)
        views.append(view)
    save_cameras(root / "cameras.json", camera_set)
    return views
