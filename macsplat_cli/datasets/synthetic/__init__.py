"""Textured synthetic scenes with exact ground truth, for tests and evaluation.

A small analytic ray caster (vectorised NumPy) renders scenes made of textured
rectangles (:class:`Quad`), oriented boxes (:class:`Box`) and spheres
(:class:`Sphere`) through a pinhole :class:`~macsplat_cli.cameras.Camera`, and
returns the image with its exact depth and normals (:func:`render`). Camera
pairs with a known baseline (:func:`orbit_pair`, :func:`forward_pair`,
:func:`pure_rotation_pair`) and the ground-truth relative pose
(:func:`relative_pose`, :func:`pose_errors`) make two-view reconstruction
measurable; :func:`transfer_points` gives exact correspondences and
:func:`write_dataset` writes a dataset folder,
:func:`write_scannetpp` a ScanNet++-layout tree. The built-in scenes
(:func:`make_scene`, :data:`SCENE_KINDS`): a room, an object on a table, small
things on a large table (``tabletop``) and an outdoor square (``outdoor``).

**World.** OpenCV-style: y points *down* (floors are at larger y than
ceilings), units are metres.

**Textures.** Every primitive surface has 2D surface coordinates ``(u, v)`` in
metres; its texture is a function of ``(u, v)`` only, so it is fixed on the
surface and identical in every view. A textured surface is its ``albedo`` plus
several octaves of coloured value noise and a few thousand random discs, rings,
rectangles, triangles and lines per square metre (at ``scale = 1``),
deterministic from the texture's seed; ``textured=False`` gives flat colours; a
periodic pattern (bricks, tiles, a grid) repeats one tile exactly, as the large
surfaces of a scene made with ``repetitive=True`` do.
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

from .orbits import (
    forward_pair,
    intrinsics,
    look_at_camera,
    orbit_cameras,
    orbit_pair,
    pose_errors,
    pure_rotation_pair,
    relative_pose,
)
from .primitives import Box, Primitive, Quad, Sphere, rotation_about
from .raycast import RayHits, SyntheticView, cast_rays, render, transfer_points
from .scannetpp import write_scannetpp
from .scenes import (
    SCENE_KINDS,
    SCENE_LAYOUTS,
    Lighting,
    Scene,
    SceneKind,
    make_scene,
    object_scene,
    outdoor_scene,
    room_scene,
    tabletop_scene,
)
from .textures import MAX_TEXTURE_SIZE, PERIODIC_PATTERNS, Texture, TexturePattern
from .writer import write_dataset

__all__ = [
    "MAX_TEXTURE_SIZE",
    "PERIODIC_PATTERNS",
    "SCENE_KINDS",
    "SCENE_LAYOUTS",
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
    "TexturePattern",
    "cast_rays",
    "forward_pair",
    "intrinsics",
    "look_at_camera",
    "make_scene",
    "object_scene",
    "orbit_cameras",
    "orbit_pair",
    "outdoor_scene",
    "pose_errors",
    "pure_rotation_pair",
    "relative_pose",
    "render",
    "room_scene",
    "rotation_about",
    "tabletop_scene",
    "transfer_points",
    "write_dataset",
    "write_scannetpp",
]
