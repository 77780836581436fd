"""``macsplat view``: the scene in a browser, through viser (Apache-2.0, the optional extra ``macsplat[view]``).

viser serves its prebuilt web client and one WebSocket from a single port; the page draws the Gaussians with
WebGL (band-0 colour) and the cameras as frusta with their photos. The panel adds what is macsplat's own: a jump
to each camera, and a "render" button that renders the current viewpoint with macsplat's rasterizer (full SH),
so the two can be compared. Nothing else is served, and viser's share link (a tunnel through a public relay) is
hidden from the panel.
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..cameras import Camera
from ..errors import InputError, MacsplatError
from ..gaussians import Gaussians
from .origin import origin_checked_serve
from .scene import ViewPose, camera_pose, short_name, splat_arrays

__all__ = [
    "PortInUseError",
    "ViewerConfig",
    "ViewerServer",
    "client_view",
    "is_loopback",
    "resolve_port",
    "viser_module",
]

logger = logging.getLogger(__name__)

EXTRA_HINT = "pip install 'macsplat[view]'"
FRUSTUM_RGB = (230, 120, 20)
"""The cameras' colour: orange, rare in photos of scenes."""


MAX_ASPECT = 100.0
"""Widest (and, inverted, tallest) client view rendered: a page is never near it; 0 or 1e9 would be no image."""
MAX_POSITION = 1e12
"""Farthest client camera position rendered (scene units; beyond it float32 view matrices lose the scene), and
the largest quaternion component taken (its length is then no overflow)."""
SHOWN_REASON_CHARS = 200
"""Why a client's view was not rendered, cut to this length in the log and the panel."""


class PortInUseError(InputError):
    """The port asked for is taken (exit code 2)."""


@dataclass(frozen=True)
class ViewerConfig:
    """How the viewer serves a scene."""

    host: str = "127.0.0.1"
    """Loopback by default: nobody else can reach the page."""
    port: int = 8080
    """0 picks a free port."""
    max_gaussians: int = 1_000_000
    """Above this the scene is refused with a ``--budget`` hint: each Gaussian is ~28 bytes on the wire and sorted
    in the page every frame; with software WebGL even 100 k take seconds a frame (``benchmarks/README.md``)."""
    render_long_side: int = 640
    """Long side, px, of the "render" button's image: about a second on two cores for 100 k Gaussians."""
    thumbnail_long_side: int = 320
    """Long side, px, of the photos shown in the frusta."""
    frustum_scale: float = 0.08
    """Frustum depth as a fraction of the median camera-to-scene distance."""


def viser_module() -> Any:
    """``import viser``, or an :class:`InputError` naming the extra to install."""
    try:
        import viser
    except ImportError as e:
        raise InputError(f"the viewer needs viser: {EXTRA_HINT}") from e
    return viser


def is_loopback(host: str) -> bool:
    """True when ``host`` names this machine's loopback only (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def resolve_port(host: str, port: int) -> int:
    """``port`` if it can be bound on ``host`` now (0: a free one, chosen by the system), else
    :class:`PortInUseError`. Checked before anything is served (viser itself would move to the next port)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no conflict
        try:
            s.bind((host, port))
        except OSError as e:
            if port and e.errno in (98, 48, 10048):  # EADDRINUSE (Linux, macOS, Windows)
                raise PortInUseError(f"port {port} on {host} is in use: pick another with --port, or --port 0") from e
            raise InputError(f"cannot serve on {host}:{port}: {e.strerror or e}") from e
        return int(s.getsockname()[1])


@dataclass
class _Scene:
    gaussians: Gaussians
    cameras: list[Camera]
    thumbnails: dict[str, np.ndarray] = field(default_factory=dict)


class ViewerServer:
    """One scene served on ``config.host:config.port`` until :meth:`stop`.

    Args:
        gaussians: the scene (the ones shown; thin it out before, see :func:`.scene.thin_out`).
        cameras: drawn as frusta, each with a "go to" entry; the first one gives the initial viewpoint.
        thumbnails: camera name → photo [h, w, 3] uint8, drawn in its frustum.
        title: shown in the panel (the scene's file name).
        config: :class:`ViewerConfig`; ``port`` must be free (:func:`resolve_port`).
    """

    def __init__(
        self,
        gaussians: Gaussians,
        cameras: list[Camera],
        *,
        thumbnails: dict[str, np.ndarray] | None = None,
        title: str = "scene",
        config: ViewerConfig = ViewerConfig(),
    ) -> None:
        if len(gaussians) > config.max_gaussians:
            raise InputError(
                f"{len(gaussians):,} Gaussians is more than the viewer takes ({config.max_gaussians:,}): "
                f"show the ones that cover most with --budget {config.max_gaussians // 2:,}"
            )
        viser = viser_module()
        self.config = config
        self._scene = _Scene(gaussians.detach().to("cpu", torch.float32), list(cameras), dict(thumbnails or {}))
        self._render_lock = threading.Lock()
        with origin_checked_serve(config.host) as guard, contextlib.redirect_stdout(io.StringIO()):
            # (viser prints a banner of its own; the CLI says the URL)
            self.server = viser.ViserServer(host=config.host, port=config.port, verbose=False)
        if not guard.installed:  # a viser that starts its server otherwise: refused, not served unchecked
            self.server.stop()
            raise InputError(
                f"the viewer cannot check its clients' web origin with viser {viser.__version__} (it starts its "
                "server otherwise than viser 1.1 does)"
            )
        self.origin_guard = guard
        # viser's share link tunnels the page through a public relay: never, whatever a client asks for
        self.server.request_share_url = lambda *args, **kwargs: None
        self.port = int(self.server.get_port())
        self.url = f"http://{'[' + config.host + ']' if ':' in config.host else config.host}:{self.port}"
        self._build(title)

    # ------------------------------------------------------------------ scene
    def _build(self, title: str) -> None:
        server, scene = self.server, self._scene
        server.gui.configure_theme(show_share_button=False, control_width="medium")
        splats = splat_arrays(scene.gaussians)
        server.scene.add_gaussian_splats(
            "/scene", centers=splats.centers, covariances=splats.covariances, rgbs=splats.rgbs,
            opacities=splats.opacities,
        )  # fmt: skip
        poses = [camera_pose(c) for c in scene.cameras]
        distance = _scene_distance(splats.centers, poses)
        if poses:
            server.scene.set_up_direction(tuple(poses[0].up))
            initial = server.initial_camera
            initial.position = tuple(poses[0].position)
            initial.look_at = tuple(poses[0].position + distance * (poses[0].look_at - poses[0].position))
            initial.up = tuple(poses[0].up)
            initial.fov = poses[0].fov_y
        for camera, pose, shown in zip(scene.cameras, poses, shown_names([c.name for c in scene.cameras])):
            handle = server.scene.add_camera_frustum(
                f"/cameras/{_node_name(shown)}", fov=pose.fov_y, aspect=pose.aspect,
                scale=self.config.frustum_scale * distance, image=scene.thumbnails.get(camera.name),
                wxyz=pose.wxyz, position=pose.position, color=FRUSTUM_RGB, thickness=2.0, thickness_units="screen",
            )  # fmt: skip
            server.scene.add_label(f"/cameras/{_node_name(shown)}/label", shown)
            handle.on_click(lambda event, pose=pose: self._go_to(event.client, pose))
        self._panel(title, len(splats), poses)

    def _panel(self, title: str, n_shown: int, poses: list[ViewPose]) -> None:
        gui, scene = self.server.gui, self._scene
        gui.add_markdown(f"**{title}** · {n_shown:,} Gaussians · {len(scene.cameras)} cameras")
        if scene.cameras:
            names = shown_names([c.name for c in scene.cameras])
            choice = gui.add_dropdown("Camera", tuple(names), initial_value=names[0])
            go = gui.add_button("Go to camera")
            pose_of = dict(zip(names, poses))
            # a value the client made up is in no camera's name: no jump
            go.on_click(lambda event: self._go_to(event.client, pose_of.get(choice.value)))
        render = gui.add_button("Render with macsplat")
        self._render_note = gui.add_markdown("Renders this viewpoint with macsplat's rasterizer (full SH).")
        self._render_image = gui.add_image(np.zeros((9, 16, 3), np.uint8), label="macsplat render", visible=False)
        render.on_click(lambda event: self._render_for(event.client))

    @staticmethod
    def _go_to(client: Any, pose: ViewPose | None) -> None:
        if client is None or pose is None:
            return
        with client.atomic():
            client.camera.wxyz = pose.wxyz
            client.camera.position = pose.position
            client.camera.fov = pose.fov_y

    def _render_for(self, client: Any) -> None:
        """The "render" button of ``client``: its viewpoint rendered into the panel. A camera that cannot be
        rendered (any client may send one) is one log line and a note in the panel; the viewer keeps serving."""
        if client is None or not self._render_lock.acquire(blocking=False):
            return
        try:
            view, why = client_view(client.camera)
            if view is None:
                self._refuse_render(why)
                return
            t0 = time.perf_counter()
            try:
                image = self.render_view(*view)
            except MacsplatError as e:
                self._refuse_render(str(e))
                return
            seconds = time.perf_counter() - t0
            self._render_image.image = image
            self._render_image.visible = True
            self._render_note.content = f"macsplat render, {image.shape[1]}×{image.shape[0]} px, {seconds:.2f} s"
        finally:
            self._render_lock.release()

    def _refuse_render(self, why: str) -> None:
        why = " ".join(why.split())[:SHOWN_REASON_CHARS]
        logger.warning("viewer: a client's view was not rendered: %s", why)
        self._render_note.content = f"cannot render this view: {why}"

    def render_view(self, wxyz: np.ndarray, position: np.ndarray, fov_y: float, aspect: float) -> np.ndarray:
        """macsplat's render of a viewer camera (camera-to-world ``wxyz`` [4], ``position`` [3], OpenCV axes;
        vertical field of view in radians; width / height) at ``config.render_long_side``. [h, w, 3] uint8"""
        from ..images import to_uint8
        from ..render import render
        from ..rotations import quat_to_rotmat_np

        long_side = self.config.render_long_side
        w, h = (
            (long_side, max(1, round(long_side / aspect)))
            if aspect >= 1
            else (max(1, round(long_side * aspect)), long_side)
        )
        fy = h / (2.0 * np.tan(fov_y / 2.0))
        K = torch.tensor([[fy, 0.0, w / 2], [0.0, fy, h / 2], [0.0, 0.0, 1.0]])
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = quat_to_rotmat_np(np.asarray(wxyz, np.float64)), position
        viewmat = torch.from_numpy(np.linalg.inv(c2w)).float()
        with torch.no_grad():
            out = render(self._scene.gaussians, viewmat, K, w, h)
        return to_uint8(out.rgb)

    # ------------------------------------------------------------------ lifetime
    def wait(self, should_stop: Callable[[], bool] = lambda: False, poll: float = 0.2) -> None:
        """Block until ``should_stop()`` (or KeyboardInterrupt, which propagates)."""
        while not should_stop():
            time.sleep(poll)

    def stop(self) -> None:
        self.server.stop()


def client_view(camera: Any) -> tuple[tuple[np.ndarray, np.ndarray, float, float] | None, str]:
    """A client's camera (viser's ``CameraHandle``: what the page last sent) as :meth:`ViewerServer.render_view`
    takes it, ``(wxyz unit [4], position [3], fov_y, aspect)``, or None and why it cannot be rendered: a value
    that is not finite or beyond :data:`MAX_POSITION`, a quaternion of (near) zero length, a field of view outside
    (0, π), an image size that is not positive or an aspect beyond :data:`MAX_ASPECT`."""
    try:
        wxyz = np.asarray(camera.wxyz, dtype=np.float64).reshape(4)
        position = np.asarray(camera.position, dtype=np.float64).reshape(3)
        fov, width, height = float(camera.fov), float(camera.image_width), float(camera.image_height)
    except (TypeError, ValueError, AttributeError) as e:
        return None, f"malformed camera ({type(e).__name__})"
    values = np.concatenate([wxyz, position, [fov, width, height]])
    if not np.isfinite(values).all() or np.abs(values[:7]).max() > MAX_POSITION:
        return None, "the camera holds non-finite or huge values"
    norm = float(np.linalg.norm(wxyz))
    if norm < 1e-6:
        return None, "the camera's orientation is a zero quaternion"
    if not 0.0 < fov < np.pi:
        return None, f"field of view {fov:.3g} rad is outside (0, π)"
    if width < 1 or height < 1 or not 1 / MAX_ASPECT <= width / height <= MAX_ASPECT:
        return None, f"image size {width:.0f}×{height:.0f} px is empty or too narrow"
    return (wxyz / norm, position, fov, width / height), ""


def shown_names(names: list[str]) -> list[str]:
    """The cameras' names as the page shows them: cut (:func:`.scene.short_name`), made unique with ``#i``."""
    out: list[str] = []
    seen: set[str] = set()
    for i, name in enumerate(names):
        shown = short_name(name)
        shown = f"{shown} #{i + 1}" if shown in seen else shown
        while shown in seen:  # a name of that form was already taken
            shown += "'"
        seen.add(shown)
        out.append(shown)
    return out


def _node_name(name: str) -> str:
    """A camera name as one scene-tree node (no slashes)."""
    return name.replace("/", "_") or "camera"


def _scene_distance(centers: np.ndarray, poses: list[ViewPose]) -> float:
    """Median distance from the first camera to the Gaussians ahead of it (1 without either)."""
    if not poses or len(centers) == 0:
        return 1.0
    p = poses[0]
    ahead = (centers - p.position) @ (p.look_at - p.position)
    ahead = ahead[ahead > 0]
    return float(np.median(ahead)) if ahead.size else 1.0
