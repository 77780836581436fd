"""The reconstruction's cameras and verified points as other tools take them (``reconstruct --export``).

The points are the matches the pose verified: for two photos the pose's inliers (``geometry.inliers``)
triangulated from the two cameras, for more the registration's tracks (``multiview.registration``), each seen by
two or more of the exported cameras — re-triangulated from the exported cameras where the joint refinement
(:mod:`.multiview.joint`) moved them, so that points and cameras agree. Everything is at the photos' original
resolution, in the world frame of the reconstruction; a photo undistorted at load gets its distortion back, with its
observations on the photo as it is.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..camera_formats import SparsePoints
from ..cameras import Camera, CameraSet
from ..distortion import distort_normalised
from .multiview.triangulate import triangulate_tracks
from .pose.geometry import homog, triangulate
from .run import Reconstruction

__all__ = ["MAX_POINT_ERROR_PX", "export_cameras", "sparse_points"]

MAX_POINT_ERROR_PX = 2.0
"""Two photos: a match whose triangulated point reprojects farther than this (working pixels, either photo) is left
out: the pose's inlier gate bounds the Sampson distance, not the point's own error."""


def export_cameras(rec: Reconstruction) -> tuple[CameraSet, list[Path]]:
    """The registered photos' cameras at their original size, named after the photo files (with their extension;
    a repeated file name gets the photo's position appended), with the distortion a photo was undistorted from;
    and the photo files, in the same order."""
    cams = rec.cameras()
    names: list[str] = []
    for k, v in enumerate(rec.views):
        name = v.path.name
        if name in names:
            name = f"{v.path.stem}_{k}{v.path.suffix}"
        names.append(name)
    out = [dataclasses.replace(c, name=n, distortion=v.undistorted) for c, n, v in zip(cams, names, rec.views)]
    return CameraSet(out, scale=cams.scale, world=cams.world), [v.path for v in rec.views]


def _observations(rec: Reconstruction) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points [P, 3], obs_image [O], obs_point [O], obs_xy [O, 2] working pixels) of the verified matches."""
    if rec.multiview is None:  # a pair: its verified matches
        assert rec.pose is not None
        g = rec.pose.geometry
        m = g.inliers
        K = (g.K0, g.K1)
        x0, x1 = (homog(xy) @ np.linalg.inv(k).T for xy, k in zip((m.xy0, m.xy1), K))
        X = triangulate(g.R, g.t, x0, x1)
        X1 = X @ g.R.T + g.t
        with np.errstate(invalid="ignore", divide="ignore"):
            err = np.maximum(*(np.linalg.norm(Xc @ k.T[:, :2] / Xc[:, 2:] - xy, axis=1)
                               for Xc, k, xy in ((X, K[0], m.xy0), (X1, K[1], m.xy1))))  # fmt: skip
            keep = np.isfinite(X).all(1) & (X[:, 2] > 0) & (X1[:, 2] > 0) & (err <= MAX_POINT_ERROR_PX)
        n = int(keep.sum())
        idx = np.arange(n)
        return (X[keep], np.r_[np.zeros(n, np.int64), np.ones(n, np.int64)], np.r_[idx, idx],
                np.r_[m.xy0[keep], m.xy1[keep]])  # fmt: skip
    assert rec.multiview is not None
    reg, ks = rec.multiview.registration, rec.multiview.map_views
    tr = reg.tracks
    image = np.full(len(reg.registered), -1, np.int64)
    image[ks] = np.arange(len(ks))
    use = reg.point_ok[tr.track] & (image[tr.view] >= 0)
    seen = np.bincount(tr.track[use], minlength=len(reg.points))
    use &= seen[tr.track] >= 2
    kept = np.flatnonzero(seen >= 2)
    renumber = np.full(len(reg.points), -1, np.int64)
    renumber[kept] = np.arange(len(kept))
    img, pt, xy = image[tr.view[use]], renumber[tr.track[use]], tr.xy[use]
    points = reg.points[kept]
    T = np.stack(rec.poses)
    if np.array_equal(T, np.stack([reg.cam_to_world(k) for k in ks])):  # the registration's cameras
        return points, img, pt, xy
    return _retriangulated(rec, T, img, pt, xy, len(kept))


def _retriangulated(
    rec: Reconstruction, T: np.ndarray, img: np.ndarray, pt: np.ndarray, xy: np.ndarray, n_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tracks re-triangulated from the cameras ``T`` (camera-to-world [C, 4, 4], refined), keeping the points
    still in front of every observing camera within the registration's error bound; same layout as
    :func:`_observations`."""
    R = np.transpose(T[:, :3, :3], (0, 2, 1))
    t = -np.einsum("cij,cj->ci", R, T[:, :3, 3])
    K = np.stack([v.K for v in rec.views])
    tri = triangulate_tracks(R, t, K, img, pt, xy, n_points, min_angle_deg=0.0)
    renumber = np.full(n_points, -1, np.int64)
    renumber[tri.ok] = np.arange(int(tri.ok.sum()))
    use = tri.ok[pt]
    return tri.points[tri.ok], img[use], renumber[pt[use]], xy[use]


def sparse_points(rec: Reconstruction, cameras: CameraSet) -> SparsePoints:
    """The verified points of ``rec`` for :func:`export_cameras`' ``cameras``: colours from the photos (mean over
    the observations), pixels at the original resolution (distorted where the camera has distortion), each point's
    mean reprojection error there."""
    X, img, pt, xy_work = _observations(rec)
    sizes = np.array([[v.width, v.height] for v in rec.views], float)
    orig = np.array([[c.width, c.height] for c in cameras], float)
    xy = xy_work * (orig[img] / sizes[img])
    rgb = np.zeros((len(X), 3))
    for k, v in enumerate(rec.views):
        sel = img == k
        ij = np.clip(np.floor(xy_work[sel]).astype(int), 0, [v.width - 1, v.height - 1])
        np.add.at(rgb, pt[sel], v.image[ij[:, 1], ij[:, 0]])
    rgb /= np.maximum(np.bincount(pt, minlength=len(X)), 1)[:, None]
    err = np.zeros(len(X))
    for k, cam in enumerate(cameras):
        sel = img == k
        Xc = X[pt[sel]] @ cam.R.T + cam.t
        np.add.at(err, pt[sel], np.linalg.norm(Xc @ cam.K.T[:, :2] / Xc[:, 2:] - xy[sel], axis=1))
        xy[sel] = _distorted(cam, xy[sel])
    err /= np.maximum(np.bincount(pt, minlength=len(X)), 1)
    return SparsePoints(X, np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8), err, img, pt, xy)


def _distorted(cam: Camera, xy: np.ndarray) -> np.ndarray:
    """Pinhole pixels of ``cam`` → the pixels of its distorted photo. [O, 2]"""
    if cam.distortion is None:
        return xy
    K = cam.K
    yn = (xy[:, 1] - K[1, 2]) / K[1, 1]
    xn = (xy[:, 0] - K[0, 2] - K[0, 1] * yn) / K[0, 0]
    xd, yd = distort_normalised(cam.distortion, xn, yn)
    return np.c_[K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]]
