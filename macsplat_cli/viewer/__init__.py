"""The browser viewer of ``macsplat view``: the scene and its cameras served to a web page (viser, optional).

``scene.py`` turns Gaussians and cameras into what the page draws (no viser import); ``server.py`` serves them.
"""

from __future__ import annotations

from .scene import SplatArrays, ViewPose, camera_pose, find_image, load_thumbnails, splat_arrays, thin_out
from .server import PortInUseError, ViewerConfig, ViewerServer, is_loopback, resolve_port, viser_module

__all__ = [
    "PortInUseError",
    "SplatArrays",
    "ViewPose",
    "ViewerConfig",
    "ViewerServer",
    "camera_pose",
    "find_image",
    "is_loopback",
    "load_thumbnails",
    "resolve_port",
    "splat_arrays",
    "thin_out",
    "viser_module",
]
