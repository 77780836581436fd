"""Lens distortion: OpenCV's models on normalised camera coordinates, and the check that one does not fold a frame.

A camera (:class:`~macsplat_cli.cameras.Camera`) may carry a :class:`Distortion`; ``reconstruct`` undistorts such
photos once, at load (:mod:`macsplat_cli.pipeline.undistort`), so every stage after it sees a pinhole image.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import CameraFileError

__all__ = ["DISTORTION_MODELS", "FOLD_MAX_ANGLE_DEG", "Distortion", "distort_normalised", "fold_problem"]

DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "opencv": ("k1", "k2", "p1", "p2", "k3"),  # cv2.undistort's distCoeffs, in this order
    "fisheye": ("k1", "k2", "k3", "k4"),  # cv2.fisheye's D
}
"""The lens models a camera may carry: model → its coefficients, in OpenCV's order."""
FOLD_MAX_ANGLE_DEG = 89.0
"""The widest ray angle off the axis the fold check follows a ray to (a fisheye's frame may reach ~90°)."""
_FOLD_RAYS, _FOLD_STEPS = 72, 4000
"""Rays (directions about the axis) and steps along each that the fold check samples."""


@dataclass(frozen=True)
class Distortion:
    """A lens's distortion in OpenCV's model: ``model`` (a key of :data:`DISTORTION_MODELS`) and its ``coeffs``
    in that order (``opencv``: k1 k2 p1 p2 k3, 5; ``fisheye``: k1 k2 k3 k4, 4), on normalised camera coordinates."""

    model: str
    coeffs: tuple[float, ...]

    @property
    def is_zero(self) -> bool:
        """No distortion at all (every coefficient 0)."""
        return all(c == 0.0 for c in self.coeffs)

    def to_dict(self) -> dict[str, Any]:
        """The ``distortion`` entry of the file format."""
        return {"model": self.model, **dict(zip(DISTORTION_MODELS[self.model], self.coeffs))}

    @classmethod
    def from_dict(cls, d: object, where: str) -> Distortion:
        """Parse a ``distortion`` entry (absent coefficients are 0).

        Raises:
            CameraFileError: not an object, an unknown model or key, or a coefficient that is not a finite number.
        """
        if not isinstance(d, Mapping):
            raise CameraFileError(f"{where} must be an object")
        model = d.get("model", "opencv")
        if model not in DISTORTION_MODELS:
            raise CameraFileError(f"{where}.model must be one of {', '.join(DISTORTION_MODELS)}, got {model!r}")
        names = DISTORTION_MODELS[model]
        unknown = sorted(set(d) - {"model", *names})
        if unknown:
            raise CameraFileError(f"{where}: {', '.join(unknown)} not a coefficient of the {model} model ({names})")
        values = []
        for k in names:
            v = d.get(k, 0.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise CameraFileError(f"{where}.{k} must be a finite number, got {v!r}")
            values.append(float(v))
        return cls(model, tuple(values))


def distort_normalised(d: Distortion, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's forward model: undistorted normalised coordinates → distorted ones (any equal shapes)."""
    if d.model == "fisheye":
        r = np.hypot(x, y)
        theta = np.arctan(r)
        k1, k2, k3, k4 = d.coeffs
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        s = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0)
        return x * s, y * s
    k1, k2, p1, p2, k3 = d.coeffs
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def fold_problem(d: Distortion, K: np.ndarray, width: int, height: int) -> str | None:
    """Why ``d`` folds the frame, or None: along every ray from the principal point, the distorted radius must grow
    with the undistorted one until it leaves the frame (else two scene directions land on one pixel)."""
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
    xn = (corners[:, 0] - K[0, 2] - K[0, 1] * (corners[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
    yn = (corners[:, 1] - K[1, 2]) / K[1, 1]
    reach = float(np.hypot(xn, yn).max())  # the frame's farthest distorted radius, normalised
    phi = np.linspace(0.0, 2 * np.pi, _FOLD_RAYS, endpoint=False)[:, None]
    r = np.tan(np.radians(FOLD_MAX_ANGLE_DEG)) * np.linspace(0.0, 1.0, _FOLD_STEPS)[None, :] ** 2
    xd, yd = distort_normalised(d, r * np.cos(phi), r * np.sin(phi))
    rd = np.hypot(xd, yd)
    inside = np.minimum.accumulate(rd <= reach * 1.0001, axis=1)  # each ray until it first leaves the frame
    grows = np.diff(rd, axis=1) > 0
    if not (grows | ~inside[:, 1:]).all():
        return (
            f"its {d.model} distortion folds the image (the distorted radius stops growing inside the frame): "
            "check the coefficients' order and signs"
        )
    return None
