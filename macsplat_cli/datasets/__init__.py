"""Evaluation data sets: posed images (+ depth) from a folder, in one of several layouts.

Every loader gives an :class:`EvalDataset`: scenes of :class:`Frame` s, each with its image
file, its ground-truth :class:`~macsplat_cli.cameras.Camera` (OpenCV axes, pixel centres at
+0.5, at the image's own resolution) and optionally a depth map (camera-space z).

Layouts (``layout="auto"`` picks the first that fits):

* ``generic`` — ``cameras.json`` (the macsplat cameras schema, see
  :mod:`macsplat_cli.cameras`), ``images/<name>.<ext>`` and optionally
  ``depth/<stem>.{png,npy,tif,tiff}``: 16-bit PNG holds ``round(depth · 1000)``
  (:func:`~macsplat_cli.images.save_depth`), ``.npy``/``.tif`` hold float depth in scene
  units; 0 = no depth. This is what :func:`macsplat_cli.datasets.synthetic.write_dataset` writes.
  The folder is one scene, or holds one scene per subfolder. ``scale`` of the cameras
  file says whether the scene is metric.
* ``scannetpp`` — ScanNet++ (:mod:`.scannetpp`): the official release tree (``<root>/data/<scene>/``,
  with ``<root>/splits/<split>.txt`` when present) or Splatt3R's ``<root>/raw`` + ``<root>/processed``
  tree. Per scene the DSLR data — undistorted images with ``transforms_undistorted.json``, or the
  fisheye ``resized_images/`` with ``transforms.json`` (or ``colmap/``), undistorted once into a cache —
  else the iPhone frames. Frames marked ``is_bad`` are dropped; poses are nerfstudio
  ``transform_matrix`` converted to OpenCV camera-to-world in the mesh frame (:func:`nerfstudio_to_opencv`).
* ``co3d-json`` — ``cameras_opencv.json`` ``{"width", "height", "views": [{"image", "K",
  "c2w"}]}`` (OpenCV axes, principal point in the +0.5 convention), as in the CO3D
  development sample; no depth, arbitrary scale.
* ``icl-nuim`` — ``color/<i>.png``, ``depth/<i>.png`` (metres × 5000), ``pose.txt`` (line i:
  ``tx ty tz qx qy qz qw``, camera-to-world) with the ICL-NUIM intrinsics (fx 481.2,
  fy −480, cx 319.5, cy 239.5 at 640×480); the left-handed rig is made right-handed with
  ``F · c2w · F``, ``F = diag(1, −1, 1, 1)``, and ``fy = +480``.
* ``nyu-rgbd`` — the same files with ``depth/<i>.pgm`` (16-bit, mm) and the NYU Depth v2
  RGB calibration (fx 518, fy 519, cx 325.5, cy 253.5; approximate poses).

Loading validates cheaply, before any evaluation work: every file exists, every image's
header is readable (no pixel decoded) and its size (EXIF orientation applied) matches its camera
and the photo limits, no two frames share an image, depth maps match their image size. A name
read from a data set's files (camera names, CO3D ``image`` paths, ScanNet++ frame and scene ids)
cannot reach outside the data set: no absolute path, no ``..``, no path separator where a plain
name is expected, no link out of the folders the layout reads (:func:`.base.member_path`,
:func:`.base.check_inside`). Problems raise :class:`~macsplat_cli.errors.DatasetError` naming
the file (and the camera).

Modules: :mod:`.base` (the types, depth reading, validation), one module per layout
(:mod:`.folder`, :mod:`.scannetpp`, :mod:`.co3d`, :mod:`.icl`), :mod:`.registry`
(:func:`detect_layout`, :func:`load_dataset`), :mod:`.coverage` (Splatt3R's visibility mask and the pairwise
coverage of a scene with depth; torch) and :mod:`.synthetic` (ray-traced scenes with exact ground truth); the
last two are imported on demand, not by this package.
"""

from __future__ import annotations

from .base import (
    LAYOUTS,
    EvalDataset,
    EvalScene,
    Frame,
    Layout,
    read_depth,
    resize_depth_nearest,
)
from .registry import detect_layout, load_dataset
from .scannetpp import nerfstudio_to_opencv, opencv_to_nerfstudio

__all__ = [
    "LAYOUTS",
    "EvalDataset",
    "EvalScene",
    "Frame",
    "Layout",
    "detect_layout",
    "load_dataset",
    "nerfstudio_to_opencv",
    "opencv_to_nerfstudio",
    "read_depth",
    "resize_depth_nearest",
]
