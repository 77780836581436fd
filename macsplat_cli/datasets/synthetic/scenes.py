"""Synthetic scenes: primitives, lighting and a viewpoint; the built-in layouts (:data:`SceneKind`).

The kinds: ``"room"`` (inside a 6 m room), ``"object"`` (an object on a table, a backdrop room around),
``"tabletop"`` (small things on a large table seen from 30–60° above: the support is nearly one plane) and
``"outdoor"`` (near objects a few metres away, buildings 40–90 m away: little parallax far away). With
``repetitive=True`` the large surfaces (walls, floors, table tops, the ground, the facades) carry one tile repeated
exactly (:data:`~.textures.PERIODIC_PATTERNS`: bricks, tiles, a grid), which matches consistently at the wrong
place; the objects keep their unique textures.

**World.** OpenCV-style: y points *down* (floors are at larger y than ceilings), units
are metres.

**Shading.** Lambertian with one directional light plus ambient,
``albedo · (ambient + diffuse · max(0, n·l))``, with ``n`` the primitive's own (outward,
or front for a quad) normal: independent of the viewpoint, so a surface point has the
same colour in every view (photo-consistency is exact up to anti-aliasing).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from ...errors import InputError
from .primitives import Box, Primitive, Quad, Sphere, _vec3, rotation_about
from .textures import PERIODIC_PATTERNS, Texture

__all__ = [
    "SCENE_KINDS",
    "SCENE_LAYOUTS",
    "Lighting",
    "Scene",
    "SceneKind",
    "make_scene",
    "object_scene",
    "outdoor_scene",
    "room_scene",
    "tabletop_scene",
]

SceneKind = Literal["room", "object", "tabletop", "outdoor"]
"""The built-in scenes (:func:`make_scene`)."""
SCENE_KINDS: tuple[SceneKind, ...] = get_args(SceneKind)


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
    r, g, b = (float(c) for c in rng.uniform(lo, hi, 3))
    return Texture(albedo=(r, g, b), seed=int(rng.integers(0, 2**31)), textured=textured, scale=scale)


def _periodic(seed: int, tag: int, repetitive: bool) -> np.random.Generator | None:
    """The generator of the periodic patterns of a ``repetitive`` scene (None: not repetitive); its own stream, so
    that the scene's layout, colours and patterns do not depend on ``repetitive``."""
    return np.random.default_rng([seed & 0xFFFFFFFF, tag, 9]) if repetitive else None


def _repeat(tex: Texture, rng: np.random.Generator | None) -> Texture:
    """``tex`` with a periodic pattern drawn from ``rng`` (``rng`` None or ``tex`` flat: ``tex`` as it is)."""
    if rng is None or not tex.textured:
        return tex
    return dataclasses.replace(tex, pattern=PERIODIC_PATTERNS[int(rng.integers(len(PERIODIC_PATTERNS)))])


def _inside_box_quads(lo: np.ndarray, hi: np.ndarray, textures: Sequence[Texture]) -> list[Primitive]:
    """Six quads bounding the box ``[lo, hi]`` with front normals pointing inwards.

    Order: floor (+y), ceiling (−y), walls −x, +x, −z, +z.
    """
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    dx, dy, dz = hi - lo
    ex, ey, ez = np.eye(3)
    quads: list[Primitive] = [
        Quad(np.array((x0, y1, z0)), dx * ex, dz * ez, textures[0]),  # floor: normal −y (up)
        Quad(np.array((x0, y0, z0)), dz * ez, dx * ex, textures[1]),  # ceiling: normal +y
        Quad(np.array((x0, y0, z0)), dy * ey, dz * ez, textures[2]),  # wall x0: normal +x
        Quad(np.array((x1, y0, z0)), dz * ez, dy * ey, textures[3]),  # wall x1: normal −x
        Quad(np.array((x0, y0, z0)), dx * ex, dy * ey, textures[4]),  # wall z0: normal +z
        Quad(np.array((x0, y0, z1)), dy * ey, dx * ex, textures[5]),  # wall z1: normal −z
    ]
    return quads


_ROOM_HALF = np.array([3.0, 1.5, 3.0])
SCENE_LAYOUTS: dict[SceneKind, tuple[np.ndarray, float, float]] = {
    "room": (np.array([0.0, 0.6, 0.0]), 2.4, 15.0),
    "object": (np.array([0.0, -0.2, 0.0]), 1.4, 25.0),
    "tabletop": (np.array([0.0, -0.03, 0.0]), 1.0, 45.0),
    "outdoor": (np.array([0.0, -0.8, 0.0]), 6.0, 8.0),
}
"""The orbit cameras' layout of each kind: (target [3], view distance in metres, elevation in degrees)."""


def room_scene(seed: int = 0, *, textured: bool = True, repetitive: bool = False) -> Scene:
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
        repetitive: the walls, floor and ceiling carry periodic patterns.
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 1])
    prng = _periodic(seed, 1, repetitive)
    floor_y = float(_ROOM_HALF[1])
    prims: list[Primitive] = _inside_box_quads(
        -_ROOM_HALF, _ROOM_HALF, [_repeat(_random_texture(rng, textured, 1.0), prng) for _ in range(6)]
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
    return _scene(prims, "room", seed)


def _scene(
    prims: list[Primitive], kind: SceneKind, seed: int, background: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> Scene:
    """A scene of ``kind`` with its layout (:data:`SCENE_LAYOUTS`) and ``background`` (RGB in [0, 1])."""
    target, dist, elev = SCENE_LAYOUTS[kind]
    return Scene(
        prims,
        background=background,
        target=target.copy(),
        view_distance=dist,
        view_elevation_deg=elev,
        name=f"{kind}-{seed}",
    )


def object_scene(seed: int = 0, *, textured: bool = True, repetitive: bool = False) -> Scene:
    """An object of about 0.5 m on a textured table, inside a large textured backdrop room.

    World: the table top is the plane ``y = 0`` (``2 × 1.4`` m, on four legs); the
    object (a box with a sphere on top, a small box and a small sphere beside it) is
    centred on the origin and rises to ``y ≈ −0.55``; the backdrop room spans
    ``x, z ∈ [−5, 5]``, ``y ∈ [−4, 0.9]`` (floor at ``y = 0.9``).

    Args:
        seed: seed of the layout, colours and textures.
        textured: ``False`` gives flat colours.
        repetitive: the backdrop room and the table carry periodic patterns.
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 2])
    prng = _periodic(seed, 2, repetitive)
    prims: list[Primitive] = _backdrop(rng, prng, textured, np.array([-5.0, -4.0, -5.0]), np.array([5.0, 0.9, 5.0]))
    table_tex = _repeat(_random_texture(rng, textured, 0.5, 0.3, 0.7), prng)
    prims.append(Box(np.array((0.0, 0.03, 0.0)), np.array((1.0, 0.03, 0.7)), None, table_tex))
    for sx in (-1, 1):
        for sz in (-1, 1):
            prims.append(Box(np.array((sx * 0.9, 0.48, sz * 0.6)), np.array((0.04, 0.42, 0.04)), None, table_tex))
    yaw = rotation_about((0, 1, 0), float(rng.uniform(-25, 25)))
    main_half = np.array([0.16, 0.15, 0.13]) * rng.uniform(0.9, 1.1, 3)
    prims.append(
        Box(np.array((0.0, -main_half[1], 0.0)), main_half, yaw, _random_texture(rng, textured, 0.25, 0.2, 0.9))
    )
    r = 0.12 * float(rng.uniform(0.9, 1.1))
    spin = rotation_about(rng.normal(size=3), float(rng.uniform(0, 360)))
    prims.append(
        Sphere(np.array((0.0, -2 * main_half[1] - r, 0.0)), r, spin, _random_texture(rng, textured, 0.25, 0.2, 0.9))
    )
    small = 0.07
    yaw2 = rotation_about((0, 1, 0), float(rng.uniform(0, 90)))
    prims.append(
        Box(
            np.array((0.3, -small, 0.12)),
            np.array((small, small, small)),
            yaw2,
            _random_texture(rng, textured, 0.25, 0.2, 0.9),
        )
    )
    r2 = 0.06
    spin2 = rotation_about(rng.normal(size=3), float(rng.uniform(0, 360)))
    prims.append(Sphere(np.array((-0.27, -r2, -0.12)), r2, spin2, _random_texture(rng, textured, 0.25, 0.2, 0.9)))
    return _scene(prims, "object", seed)


def _backdrop(
    rng: np.random.Generator, prng: np.random.Generator | None, textured: bool, lo: np.ndarray, hi: np.ndarray
) -> list[Primitive]:
    """A large backdrop room ``[lo, hi]`` around a table (textures at scale 1.5)."""
    return _inside_box_quads(lo, hi, [_repeat(_random_texture(rng, textured, 1.5), prng) for _ in range(6)])


def tabletop_scene(seed: int = 0, *, textured: bool = True, repetitive: bool = False) -> Scene:
    """Three to five small things (3–16 cm) on a large 3 × 2 m textured table, inside a backdrop room.

    Seen from the layout's 30–60° above the table (:data:`SCENE_LAYOUTS`: 1 m from the centre, 45° by default),
    most of an image is the table: the matches lie nearly on one plane, the hard case of the pose (homography
    against essential matrix). World: the table top is the plane ``y = 0``, ``x ∈ [−1.5, 1.5]``,
    ``z ∈ [−1, 1]``; the things stand within 0.4 m of the origin and rise to at most ``y ≈ −0.16``; the
    backdrop room spans ``x, z ∈ [−5, 5]``, ``y ∈ [−3, 0.8]``.

    Args:
        seed: seed of the layout, colours and textures.
        textured: ``False`` gives flat colours.
        repetitive: the table and the backdrop room carry periodic patterns.
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 6])
    prng = _periodic(seed, 6, repetitive)
    prims = _backdrop(rng, prng, textured, np.array([-5.0, -3.0, -5.0]), np.array([5.0, 0.8, 5.0]))
    table_tex = _repeat(_random_texture(rng, textured, 0.5, 0.3, 0.75), prng)
    prims.append(Box(np.array((0.0, 0.03, 0.0)), np.array((1.5, 0.03, 1.0)), None, table_tex))
    for sx in (-1, 1):
        for sz in (-1, 1):
            prims.append(Box(np.array((sx * 1.4, 0.44, sz * 0.9)), np.array((0.04, 0.38, 0.04)), None, table_tex))
    n = int(rng.integers(3, 6))
    start = rng.uniform(0, 2 * np.pi)
    for i in range(n):
        ang = start + i * 2 * np.pi / n + rng.uniform(-0.3, 0.3)
        rad = rng.uniform(0.08, 0.35)
        x, z = rad * math.cos(ang), rad * math.sin(ang)
        tex = _random_texture(rng, textured, 0.2, 0.15, 0.9)
        shape = int(rng.integers(0, 3))
        if shape == 0:  # a box (a cup, a tin)
            half = rng.uniform([0.02, 0.02, 0.02], [0.05, 0.08, 0.05])
            rot = rotation_about((0, 1, 0), float(rng.uniform(0, 90)))
            prims.append(Box(np.array((x, -half[1], z)), half, rot, tex))
        elif shape == 1:  # a ball
            r = float(rng.uniform(0.025, 0.06))
            spin = rotation_about(rng.normal(size=3), float(rng.uniform(0, 360)))
            prims.append(Sphere(np.array((x, -r, z)), r, spin, tex))
        else:  # a flat thing (a book)
            half = rng.uniform([0.06, 0.008, 0.04], [0.1, 0.02, 0.07])
            rot = rotation_about((0, 1, 0), float(rng.uniform(0, 90)))
            prims.append(Box(np.array((x, -half[1], z)), half, rot, tex))
    return _scene(prims, "tabletop", seed)


_SKY = (0.62, 0.74, 0.9)
"""The colour of rays that hit nothing outdoors (flat: no features)."""


def _ground(rng: np.random.Generator, prng: np.random.Generator | None, textured: bool) -> list[Primitive]:
    """The ground plane ``y = 0``: a near patch of 3 × 3 tiles of 12 m (fine textures, 1.2 cm texels) and four
    coarse strips out to 120 m (30 cm texels)."""
    ex, ez = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    prims: list[Primitive] = []
    for i in range(3):
        for j in range(3):
            tex = _repeat(_random_texture(rng, textured, 1.0, 0.3, 0.6), prng)
            prims.append(Quad(np.array((-18.0 + 12 * i, 0.0, -18.0 + 12 * j)), 12 * ez, 12 * ex, tex))  # normal −y (up)
    far, near = 120.0, 18.0
    strips = [  # (corner, x extent, z extent): left, right, back, front
        ((-far, -far), far - near, 2 * far),
        ((near, -far), far - near, 2 * far),
        ((-near, -far), 2 * near, far - near),
        ((-near, near), 2 * near, far - near),
    ]
    for (x0, z0), dx, dz in strips:
        tex = _repeat(_random_texture(rng, textured, 4.0, 0.3, 0.6), prng)
        prims.append(Quad(np.array((x0, 0.0, z0)), dz * ez, dx * ex, tex))
    return prims


def outdoor_scene(seed: int = 0, *, textured: bool = True, repetitive: bool = False) -> Scene:
    """A square: things a few metres from the cameras, posts and trees at 10–25 m, buildings at 40–90 m, sky.

    The depth range of one view spans two orders of magnitude: the cameras (6 m from the centre, about 1.6 m above
    the ground, :data:`SCENE_LAYOUTS`) see the near things at 2–10 m and the facades at 35–95 m, whose parallax is
    small. World: the ground is the plane ``y = 0`` out to 120 m; five near things (boxes of 0.6–1.8 m, balls)
    stand within 3.5 m of the origin; six posts with a round crown stand 10–25 m out; ten buildings (16–28 m wide,
    8–24 m high) ring the square 40–80 m from the origin, their faces seen from it; rays that hit nothing are sky
    (a flat colour).

    Args:
        seed: seed of the layout, colours and textures.
        textured: ``False`` gives flat colours.
        repetitive: the ground and the facades carry periodic patterns.
    """
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 7])
    prng = _periodic(seed, 7, repetitive)
    prims = _ground(rng, prng, textured)
    start = rng.uniform(0, 2 * np.pi)
    for i in range(5):  # near things
        ang, rad = start + i * 2 * np.pi / 5 + rng.uniform(-0.4, 0.4), rng.uniform(0.5, 2.8)
        x, z = rad * math.cos(ang), rad * math.sin(ang)
        tex = _random_texture(rng, textured, 0.5, 0.15, 0.9)
        if rng.uniform() < 0.7:
            half = rng.uniform([0.3, 0.3, 0.3], [0.9, 0.8, 0.6])
            prims.append(
                Box(np.array((x, -half[1], z)), half, rotation_about((0, 1, 0), float(rng.uniform(0, 90))), tex)
            )
        else:
            r = float(rng.uniform(0.3, 0.6))
            prims.append(
                Sphere(np.array((x, -r, z)), r, rotation_about(rng.normal(size=3), float(rng.uniform(0, 360))), tex)
            )
    for _ in range(6):  # posts with a crown
        ang, rad = rng.uniform(0, 2 * np.pi), rng.uniform(10.0, 25.0)
        x, z = rad * math.cos(ang), rad * math.sin(ang)
        height, crown = float(rng.uniform(2.0, 4.0)), float(rng.uniform(0.8, 1.8))
        prims.append(
            Box(
                np.array((x, -height / 2, z)),
                np.array((0.15, height / 2, 0.15)),
                None,
                _random_texture(rng, textured, 1.0),
            )
        )
        spin = rotation_about(rng.normal(size=3), float(rng.uniform(0, 360)))
        prims.append(
            Sphere(np.array((x, -height - crown, z)), crown, spin, _random_texture(rng, textured, 2.0, 0.1, 0.6))
        )
    start = rng.uniform(0, 2 * np.pi)
    for i in range(10):  # buildings, their long side towards the square
        ang, rad = start + i * 2 * np.pi / 10 + rng.uniform(-0.15, 0.15), rng.uniform(40.0, 80.0)
        half = rng.uniform([8.0, 4.0, 5.0], [14.0, 12.0, 10.0])
        centre = np.array([(rad + half[2]) * math.cos(ang), -half[1], (rad + half[2]) * math.sin(ang)])
        yaw = rotation_about((0, 1, 0), -math.degrees(ang) + 90.0)  # local z along the radius
        prims.append(Box(centre, half, yaw, _repeat(_random_texture(rng, textured, 8.0, 0.3, 0.85), prng)))
    return _scene(prims, "outdoor", seed, background=_SKY)


def make_scene(kind: SceneKind, seed: int = 0, *, textured: bool = True, repetitive: bool = False) -> Scene:
    """The built-in scene ``kind`` (:data:`SCENE_KINDS`) of ``seed``.

    Args:
        kind: the layout.
        seed: seed of the layout, colours and textures.
        textured: ``False`` gives flat colours.
        repetitive: the large surfaces carry periodic patterns (module docstring).
    """
    builders: dict[SceneKind, Callable[..., Scene]] = {
        "room": room_scene,
        "object": object_scene,
        "tabletop": tabletop_scene,
        "outdoor": outdoor_scene,
    }
    if kind not in builders:
        raise InputError(f"unknown synthetic scene kind {kind!r}; use one of {', '.join(SCENE_KINDS)}")
    return builders[kind](seed, textured=textured, repetitive=repetitive)
