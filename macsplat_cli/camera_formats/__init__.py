"""Camera exchange formats: COLMAP models (text written; text and binary read), nerfstudio ``transforms.json``, and
their sparse points; any camera input (a cameras file or a COLMAP model folder) through :func:`load_camera_input`.

The conversions are exact and round-trip with :mod:`macsplat_cli.cameras`; the conventions (axes, pixel centres,
pose direction) are documented on each function.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..cameras import CameraSet, load_cameras
from .colmap import COLMAP_MODELS, read_colmap_model, read_colmap_text, write_colmap_text
from .nerfstudio import read_nerfstudio, write_nerfstudio
from .photos import cameras_for_photos
from .points import SparsePoints, write_point_ply

__all__ = [
    "COLMAP_MODELS",
    "SparsePoints",
    "cameras_for_photos",
    "load_camera_input",
    "read_colmap_model",
    "read_colmap_text",
    "read_nerfstudio",
    "write_colmap_text",
    "write_nerfstudio",
    "write_point_ply",
]


def load_camera_input(path: str | os.PathLike[str]) -> CameraSet:
    """The cameras of ``--intrinsics`` / ``--poses``: a cameras file (:func:`~macsplat_cli.cameras.load_cameras`),
    or a COLMAP model folder (:func:`read_colmap_model`; its frame and scale kept, named ``"colmap"``).

    Raises:
        CameraFileError: the file or model is missing or malformed (the message names it and the problem).
    """
    p = Path(path)
    return read_colmap_model(p) if p.is_dir() else load_cameras(p)
