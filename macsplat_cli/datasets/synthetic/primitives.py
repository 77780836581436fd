"""Ray-castable primitives of the synthetic scenes: textured quads, oriented boxes, spheres.

Every primitive surface has 2D surface coordinates ``(u, v)`` in metres; its texture
(:class:`~.textures.Texture`) is a function of ``(u, v)`` only, so it is fixed on the
surface and identical in every view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from ...errors import InputError
from .textures import Texture, _sample

__all__ = ["Box", "Primitive", "Quad", "Sphere", "rotation_about"]

_EPS_T = 1e-6
"""Smallest accepted ray parameter (hits closer than this to the camera are ignored)."""


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


def _frame(prim: Box | Sphere) -> np.ndarray:
    """``prim.rotation`` after ``__post_init__``, which replaced ``None`` with the identity. [3, 3]"""
    return cast(np.ndarray, prim.rotation)


def rotation_about(axis: Sequence[float] | np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation matrix of ``angle_deg`` degrees about ``axis`` (right-handed, Rodrigues). [3, 3]"""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    th = math.radians(angle_deg)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * (Kx @ Kx)


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
        R, h = _frame(self), self.half_size
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
        axis = np.where(outside, k_near, k_far)
        d_k = np.choose(axis, d)
        # entering through the face turned towards the ray (the − face when d_k > 0); leaving through the other
        positive = np.where(outside, d_k < 0, d_k > 0)
        return t, (2 * axis + positive).astype(np.int8)

    def surface(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, h = _frame(self), self.half_size
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
        q = [_dot(_frame(self)[:, k], normals) for k in range(3)]  # texture-frame directions
        theta = np.arccos(np.clip(q[1], -1.0, 1.0))
        phi = np.arctan2(q[0], q[2])
        u = r * phi * np.sin(theta) + math.pi * r
        v = r * theta
        return normals, _sample(self.texture, self._cache, 0, 2 * math.pi * r, math.pi * r, u, v)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.center.copy(), self.radius
