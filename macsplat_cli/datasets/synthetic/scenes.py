"""Synthetic scenes: primitives, lighting and a viewpoint; the built-in room and object-on-a-table layouts.

**World.** OpenCV-style: y points *down* (floors are at larger y than ceilings), units
are metres.

**Shading.** Lambertian with one directional light plus ambient,
``albedo · (ambient + diffuse · max(0, n·l))``, with ``n`` the primitive's own (outward,
or front for a quad) normal: independent of the viewpoint, so a surface point has the
same colour in every view (photo-consistency is exact up to anti-aliasing).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ...errors import InputError
from .primitives import Box, Primitive, Quad, Sphere, _vec3, rotation_about
from .textures import Texture

__all__ = ["Lighting", "Scene", "SceneKind", "make_scene", "object_scene", "room_scene"]

SceneKind = Literal["room", "object"]


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
