"""Build ``examples/motorcycle/`` from the copy of the Middlebury 2014 "Motorcycle" pair
that scikit-image ships (``skimage.data.stereo_motorcycle()``, no download).

    python examples/make_motorcycle_example.py

Writes the left and right images downscaled to 640 px wide (JPEG, quality 95) and
``cameras.json`` with the calibrated intrinsics and the true relative pose (metric, mm),
so the example can also be run with ``--intrinsics`` and compared with ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image
from skimage.data import stereo_motorcycle

from macsplat_cli.cameras import Camera, CameraSet, save_cameras

WIDTH = 640
# Middlebury calib.txt for Motorcycle ÷ 4 (the resolution scikit-image ships), OpenCV
# convention (pixel centres on integers): f, cx0, cy, doffs = cx1 − cx0, baseline in mm.
F, CX0, CY, DOFFS, BASELINE_MM = 994.978, 311.193, 254.877, 31.086, 193.001


def main() -> None:
    out = Path(__file__).parent / "motorcycle"
    out.mkdir(exist_ok=True)
    left, right, _ = stereo_motorcycle()
    h, w = left.shape[:2]
    s = WIDTH / w
    size = (WIDTH, round(h * s))
    cams = []
    for name, img, cx in (("left.jpg", left, CX0), ("right.jpg", right, CX0 + DOFFS)):
        Image.fromarray(img).resize(size, Image.LANCZOS).save(out / name, quality=95)
        # +0.5: macsplat's pixel centres; then scale both axes to the new size
        K = np.array([[F * s, 0.0, (cx + 0.5) * s], [0.0, F * size[1] / h, (CY + 0.5) * size[1] / h], [0, 0, 1.0]])
        c2w = np.eye(4)
        if name == "right.jpg":
            c2w[0, 3] = BASELINE_MM  # the right camera sits 193 mm to the right (x) of the left one
        cams.append(Camera(name, size[0], size[1], K, c2w))
    save_cameras(out / "cameras.json", CameraSet(cams, scale="metric", world="left camera, millimetres"))
    print(f"wrote {out} ({size[0]}x{size[1]})")


if __name__ == "__main__":
    main()
