"""Synthetic planar two-view matches for the pose stage's stress cases (issue 14).

A tilted plane seen with a random motion (the original stress family, ~5° between the views) or a table photographed
twice from above, optionally with objects on it whose matches partly fall below the confidence gate
(``Matches.below_gate``), and outliers. Used by ``benchmarks/pose_stress.py`` and
``tests/pipeline/pose/test_pose_planar.py``.

The matches are plain arrays (:class:`PlanarMatches`): the data sets sit below the pipeline, so the callers build
the pipeline's ``Matches`` from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["H", "K", "W", "PlanarMatches", "planar_case", "project"]

W, H = 320, 240
K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
"""The cases' image size and intrinsics."""


def project(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    X1 = X @ R.T + t
    p0, p1 = X @ K.T, X1 @ K.T
    xy0, xy1 = p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]
    ok = (X1[:, 2] > 0.1) & np.all((xy0 >= 0) & (xy0 < (W, H)) & (xy1 >= 0) & (xy1 < (W, H)), axis=1)
    return xy0, xy1, ok


@dataclass
class PlanarMatches:
    """The matches of one planar case, as plain arrays (a caller makes ``pipeline.types.Matches`` of them).

    Attributes:
        xy0: pixel positions in view 0 (pixel centres at +0.5). [M, 2] float64
        xy1: the matching positions in view 1. [M, 2] float64
        below_gate: the matches that fall below the confidence gate (their own ``xy0``/``xy1``), or None.
    """

    xy0: np.ndarray
    xy1: np.ndarray
    below_gate: PlanarMatches | None = None


def _motion(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = rng.normal(size=3)
    R = cv2.Rodrigues(a / np.linalg.norm(a) * math.radians(rng.uniform(0, 20)))[0]
    t = rng.normal(size=3)
    return R, t / np.linalg.norm(t) * 0.5, rng.uniform(-0.5, 0.5, 2)


def _look_at(eye: np.ndarray, target: np.ndarray, roll_deg: float) -> np.ndarray:
    """World-to-camera rotation of a camera at ``eye`` looking at ``target`` (world y up, camera y down). [3, 3]"""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    Rc = np.stack([x, y, z])
    return cv2.Rodrigues(np.array([0.0, 0.0, math.radians(roll_deg)]))[0] @ Rc


def _table_top(
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """A table (6 × 4 units, the plane y = 0) photographed twice from 6 units away, 30–60° above it, the second
    photo 10–30° further round (both aimed near the table's centre, ±0.3 units, roll ±3°).

    Returns:
        ``(R, t, to_cam0, table, up)``: the relative pose, the world → camera-0 map ``(Rc0, C0)`` (rotation [3, 3],
        centre [3]), random table points [1200, 3] (world) and the table's normal (world).
    """
    el0 = rng.uniform(30, 60)
    az0 = rng.uniform(0, 360)
    step = rng.uniform(10, 30) * rng.choice([-1, 1])
    el1 = el0 + rng.uniform(-5, 5)

    def eye(az: float, el: float) -> np.ndarray:
        a, e = math.radians(az), math.radians(el)
        return 6.0 * np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])

    C0, C1 = eye(az0, el0), eye(az0 + step, el1)
    Rc0 = _look_at(C0, rng.uniform(-0.3, 0.3, 3) * (1, 0, 1), rng.uniform(-3, 3))
    Rc1 = _look_at(C1, rng.uniform(-0.3, 0.3, 3) * (1, 0, 1), rng.uniform(-3, 3))
    R = Rc1 @ Rc0.T
    t = Rc1 @ (C0 - C1)
    table = np.c_[rng.uniform(-3, 3, 1200), np.zeros(1200), rng.uniform(-2, 2, 1200)]
    return R, t, (Rc0, C0), table, np.array([0.0, 1.0, 0.0])


def planar_case(seed: int, off: float | None, motion: str = "random") -> tuple[PlanarMatches, np.ndarray, np.ndarray]:
    """One planar case: (matches, possibly with ``below_gate``; true R; true t).

    ``motion``: ``"random"`` (the original: axis random, rotation 0–20°, translation 0.5 in a random direction,
    a tilted plane 6 units ahead; about 5° between the views) or ``"table"`` (:func:`_table_top`, 10–30°).
    """
    rng = np.random.default_rng(seed)
    if motion == "random":
        R, t, tilt = _motion(rng)
        X = np.c_[rng.uniform(-3, 3, (1200, 2)), np.zeros(1200)]
        X[:, 2] = 6 - X[:, :2] @ tilt
        normal = np.array([tilt[0], tilt[1], 1.0])
        normal /= -np.linalg.norm(normal)  # towards camera 0
    else:
        R, t, (Rc0, C0), table, up = _table_top(rng)
        X = (table - C0) @ Rc0.T
        normal = Rc0 @ up
    if off is None:  # the original family: 200 exact plane points and nothing else
        xy0, xy1, ok = project(X, R, t)
        xy0, xy1 = xy0[ok][:200], xy1[ok][:200]
        xy0, xy1 = xy0 + rng.normal(0, 0.3, xy0.shape), xy1 + rng.normal(0, 0.3, xy1.shape)
        return PlanarMatches(xy0, xy1), R, t
    is_off = rng.uniform(size=len(X)) < off
    height = rng.uniform(0.1, 1.0, len(X))  # objects on the table (1 unit ≈ 20 cm on a 1.2 m table)
    X = np.where(is_off[:, None], X + height[:, None] * normal, X)
    xy0, xy1, ok = project(X, R, t)
    xy0, xy1, is_off = xy0[ok][:300], xy1[ok][:300], is_off[ok][:300]
    gated = np.zeros(len(xy0), bool)
    cand = np.flatnonzero(~is_off | (rng.uniform(size=len(xy0)) < 0.5))  # half the off-plane ones fail the gate
    gated[cand[:200]] = True
    g0 = xy0[gated] + rng.normal(0, 0.3, (gated.sum(), 2))
    g1 = xy1[gated] + rng.normal(0, 0.3, (gated.sum(), 2))
    n_out = len(g0) // 20
    g0 = np.concatenate([g0, rng.uniform((0, 0), (W, H), (n_out, 2))])
    g1 = np.concatenate([g1, rng.uniform((0, 0), (W, H), (n_out, 2))])
    b0 = np.concatenate([xy0[~gated] + rng.normal(0, 0.6, ((~gated).sum(), 2)), rng.uniform((0, 0), (W, H), (300, 2))])
    b1 = np.concatenate([xy1[~gated] + rng.normal(0, 0.6, ((~gated).sum(), 2)), rng.uniform((0, 0), (W, H), (300, 2))])
    return PlanarMatches(g0, g1, below_gate=PlanarMatches(b0, b1)), R, t
