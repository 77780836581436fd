"""Cameras around a synthetic scene (orbits, forward motion, pure rotation) and their ground-truth relative pose.

Camera pairs with a known baseline (:func:`orbit_pair`, :func:`forward_pair`,
:func:`pure_rotation_pair`) and the ground-truth relative pose (:func:`relative_pose`,
:func:`pose_errors`) make two-view reconstruction measurable.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ...cameras import Camera
from ...errors import InputError
from ...metrics import rotation_error_deg, translation_direction_error_deg
from .primitives import _vec3, rotation_about
from .scenes import SCENE_KINDS, SCENE_LAYOUTS, Scene, SceneKind

__all__ = [
    "forward_pair",
    "intrinsics",
    "look_at_camera",
    "orbit_cameras",
    "orbit_pair",
    "pose_errors",
    "pure_rotation_pair",
    "relative_pose",
]


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
    if scene not in SCENE_LAYOUTS:
        raise InputError(f"unknown synthetic scene kind {scene!r}; use one of {', '.join(SCENE_KINDS)}")
    target, dist, elev = SCENE_LAYOUTS[scene]
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
        scene: a scene kind (:data:`~.scenes.SceneKind`) or a :class:`Scene` (its
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
    elevation_deg: float | None = None,
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
        scene: a scene kind (:data:`~.scenes.SceneKind`) or a :class:`Scene`.
        angle_deg: angle between the optical axes in degrees, in [0, 180 − 2·elevation).
        width: image width.
        height: image height.
        fov_deg: horizontal field of view.
        seed: seed of the jitter.
        jitter: ``False`` for the symmetric pair without jitter (azimuths ±angle/2).
        names: camera names.
        elevation_deg: elevation above the target (default: the scene's).

    Returns:
        ``(camera0, camera1)``.
    """
    target, dist, elev = _scene_layout(scene)
    elev = elev if elevation_deg is None else float(elevation_deg)
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
        scene: a scene kind (:data:`~.scenes.SceneKind`) or a :class:`Scene`.
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


def relative_pose(cam0: Camera, cam1: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pose of camera 1 in camera 0's frame: ``X_cam1 = R · X_cam0 + t``.

    This is what an essential-matrix estimate recovers (``t`` up to scale, here in
    world units): ``E = [t]× R``.

    Returns:
        ``(R, t)``: rotation [3, 3] and translation [3].
    """
    T = cam1.world_to_cam @ cam0.cam_to_world
    return T[:3, :3].copy(), T[:3, 3].copy()


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
    return rotation_error_deg(R_est, R_gt), translation_direction_error_deg(t_est, t_gt)
