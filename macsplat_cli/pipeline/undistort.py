"""Stage 1's lens undistortion: a photo whose camera carries distortion becomes a pinhole photo, once, at load.

The undistorted photo keeps the camera's own ``K`` (and size): a pixel of it shows the direction that ``K`` gives it,
sampled from the distorted photo where OpenCV's model (:mod:`macsplat_cli.distortion`) puts that direction
(bilinear). Pixels whose direction falls outside the photo get alpha 0, so the view's mask leaves them out, and the
photo's nearest edge colour (not black): a black border would be the same hard edge at the same pixels of every
photo, and its keypoints would match as if nothing moved (on the NYU pairs that pulled the pose 14–19° off). Every
later stage (keypoints, pose, depth, Gaussians, refinement's photos) works on a pinhole image.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from ..cameras import Camera
from ..distortion import Distortion
from ..images import LoadedImage

__all__ = ["undistort_maps", "undistort_photo"]

logger = logging.getLogger(__name__)


def undistort_maps(K: np.ndarray, distortion: Distortion, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the undistorted ``width × height`` image (pinhole ``K``, pixel centres at +0.5), where
    to sample the distorted photo, in OpenCV's pixel indices (centres on integers). [H, W] float32 each"""
    K_cv = K.copy()  # OpenCV's pixel centres are on integers: the same K shifted by half a pixel
    K_cv[0, 2] -= 0.5
    K_cv[1, 2] -= 0.5
    D = np.asarray(distortion.coeffs, np.float64)
    size = (int(width), int(height))
    if distortion.model == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(K_cv, D, np.eye(3), K_cv, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K_cv, D, None, K_cv, size, cv2.CV_32FC1)


def undistort_photo(img: LoadedImage, cam: Camera) -> LoadedImage:
    """``img`` undistorted to ``cam``'s pinhole ``K`` (rescaled to the photo's size), its alpha following (0 where
    the pixel's direction is outside the photo); ``img`` itself when the camera has no distortion."""
    d = cam.distortion
    if d is None or d.is_zero:
        return img
    K = cam.rescaled(img.width, img.height).K
    mx, my = undistort_maps(K, d, img.width, img.height)
    rgb = cv2.remap(img.rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    alpha0 = img.alpha if img.alpha is not None else np.ones((img.height, img.width), np.float32)
    alpha = cv2.remap(alpha0, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    logger.debug("%s: undistorted (%s %s)", img.path.name, d.model, list(d.coeffs))
    return dataclasses.replace(img, rgb=np.ascontiguousarray(rgb, np.float32), alpha=alpha.astype(np.float32))
