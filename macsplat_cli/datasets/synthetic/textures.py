"""Procedural surface textures of the synthetic scenes: value noise and random shapes, or a repeated tile.

A textured surface is its ``albedo`` plus several octaves of coloured value noise and a few
thousand random discs, rings, rectangles, triangles and lines per square metre (at
``scale = 1``), deterministic from the texture's seed. A *periodic* texture (``pattern``
``"bricks"``, ``"tiles"`` or ``"grid"``) is one small tile repeated exactly over the surface:
every period looks the same, so its descriptors match consistently at the wrong place (the
hard case of repetitive scenes). Textures are rasterised once per surface (a few millimetres
per texel, at most :data:`MAX_TEXTURE_SIZE` texels a side), cached on the primitive and in the process (the same
scene built again rasterises nothing: :data:`SHARED_CACHE_BYTES`), and sampled bilinearly.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal, get_args

import cv2
import numpy as np

__all__ = ["MAX_TEXTURE_SIZE", "PERIODIC_PATTERNS", "Texture", "TexturePattern"]

TexturePattern = Literal["random", "bricks", "tiles", "grid"]
"""A texture's pattern: random noise and shapes (unique everywhere), or one tile repeated exactly."""
PERIODIC_PATTERNS: tuple[TexturePattern, ...] = tuple(p for p in get_args(TexturePattern) if p != "random")

MAX_TEXTURE_SIZE = 1024
"""Largest side of a rasterised surface texture, in texels."""
SHARED_CACHE_BYTES = 256 << 20
"""The process-wide cache of rasterised textures (least recently used first out): scenes are rebuilt often (every
``make_scene``, every synthetic sample pair of ``export-onnx``, every evaluation case) and a room's textures take
~0.5 s of CPU to rasterise; 256 MB holds a few scenes' (a 1024² texture is 12 MB)."""
_TEXEL = 0.004
"""Texel size in metres of a ``scale = 1`` texture (larger for surfaces over 4 m)."""
_COARSE_NOISE = ((0.64, 0.16), (0.32, 0.12), (0.16, 0.09), (0.08, 0.07))
"""(cell size in metres at scale 1, amplitude) of the noise octaves under the shapes."""
_FINE_NOISE = ((0.04, 0.05), (0.02, 0.04))
"""(cell size, amplitude) of the noise octaves over the shapes."""
_SHAPE_SPACING = 0.1
"""One random shape per ``(spacing · scale)²`` square metres."""
_SHAPE_RADIUS = (0.012, 0.12)
"""Range of shape radii in metres at scale 1 (log-uniform)."""
_MAX_SHAPES = 8000
_PERIOD = {"bricks": (0.24, 0.16), "tiles": (0.3, 0.3), "grid": (0.1, 0.1)}
"""(width, height) in metres at scale 1 of the repeated tile of each periodic pattern (bricks: two courses)."""
_JOINT = 0.012
"""Width in metres at scale 1 of the mortar, grout and grid lines of the periodic patterns."""


@dataclass(frozen=True)
class Texture:
    """A procedural surface texture, a function of the surface coordinates ``(u, v)`` in metres.

    Attributes:
        albedo: base RGB colour in [0, 1].
        seed: seed of the random pattern (with the surface's face index).
        textured: ``False`` for a flat ``albedo`` (no pattern).
        scale: size of the pattern features relative to the default (noise cells of
            2 cm to 64 cm, shapes of 1.2 cm to 12 cm radius, 4 mm texels at ``scale = 1``).
        pattern: ``"random"`` (noise and shapes), or a tile repeated exactly: ``"bricks"``
            (24 × 8 cm bricks, courses offset by half a brick), ``"tiles"`` (30 cm square tiles, one motif
            each) or ``"grid"`` (10 cm grid lines); sizes at ``scale = 1``.
    """

    albedo: tuple[float, float, float] = (0.6, 0.6, 0.6)
    seed: int = 0
    textured: bool = True
    scale: float = 1.0
    pattern: TexturePattern = "random"


def _draw_shapes(
    canvas: np.ndarray, rng: np.random.Generator, albedo: np.ndarray, area_m2: float, scale: float, texel: float
) -> None:
    """Draw random discs, rings, rectangles, triangles and line segments on an 8-bit RGB canvas, anti-aliased."""
    h, w = canvas.shape[:2]
    n = min(_MAX_SHAPES, int(area_m2 / (_SHAPE_SPACING * scale) ** 2))
    log_r = np.log(np.asarray(_SHAPE_RADIUS) * scale / texel)
    kinds = rng.integers(0, 5, n).tolist()
    xs, ys = rng.uniform(0.0, w, n), rng.uniform(0.0, h, n)
    rs = np.exp(rng.uniform(log_r[0], log_r[1], n))
    colors = (
        np.clip(np.rint((albedo * 0.25 + rng.uniform(0.02, 0.98, (n, 3)) * 0.75) * 255), 0, 255).astype(int).tolist()
    )
    angles = rng.uniform(0.0, 2.0 * np.pi, n)
    p1, p2 = rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n)
    tri = angles[:, None] + np.array([0.0, 2.1, 4.2]) + rng.uniform(-0.5, 0.5, (n, 3))
    sub = 16.0  # cv2 drawing with shift=4: coordinates in 1/16 texel
    cx, cy, rr = (xs * sub).astype(int).tolist(), (ys * sub).astype(int).tolist(), (rs * sub).astype(int).tolist()
    aa = cv2.LINE_AA
    for i, kind in enumerate(kinds):
        color, r = tuple(colors[i]), float(rs[i])
        if kind == 0:  # disc
            cv2.circle(canvas, (cx[i], cy[i]), rr[i], color, -1, aa, 4)
        elif kind == 1:  # ring
            cv2.circle(canvas, (cx[i], cy[i]), rr[i], color, max(1, round(r * (0.15 + 0.25 * p1[i]))), aa, 4)
        elif kind == 2:  # rotated rectangle
            size = (2 * r * (0.4 + 0.6 * p1[i]), 2 * r * (0.4 + 0.6 * p2[i]))
            pts = cv2.boxPoints(((float(xs[i]), float(ys[i])), size, float(np.degrees(angles[i]))))
            cv2.fillPoly(canvas, [np.rint(pts * sub).astype(np.int32)], color, aa, 4)
        elif kind == 3:  # triangle
            pts = np.stack([xs[i] + r * np.cos(tri[i]), ys[i] + r * np.sin(tri[i])], -1)
            cv2.fillPoly(canvas, [np.rint(pts * sub).astype(np.int32)], color, aa, 4)
        else:  # line segment
            dx, dy = 2.0 * r * math.cos(angles[i]) * sub, 2.0 * r * math.sin(angles[i]) * sub
            q0 = (int(cx[i] - dx), int(cy[i] - dy))
            q1 = (int(cx[i] + dx), int(cy[i] + dy))
            cv2.line(canvas, q0, q1, color, max(1, round(r * (0.1 + 0.2 * p1[i]))), aa, 4)


def _texture_image(tex: Texture, width_m: float, height_m: float, key: int) -> tuple[np.ndarray, float]:
    """Rasterise ``tex`` over ``[0, width_m] × [0, height_m]`` metres.

    Returns:
        ``(image, texel)``: float32 RGB ``[h, w, 3]`` whose texel ``(i, j)`` covers
        ``[j·texel, (j+1)·texel] × [i·texel, (i+1)·texel]``, and the texel size in metres.
    """
    s = float(tex.scale)
    texel = max(_TEXEL * s, max(width_m, height_m) / MAX_TEXTURE_SIZE)
    w = max(2, math.ceil(width_m / texel))
    h = max(2, math.ceil(height_m / texel))
    if tex.pattern != "random":
        tile = _periodic_tile(tex, texel, key)
        reps = (math.ceil(h / tile.shape[0]), math.ceil(w / tile.shape[1]), 1)
        return np.ascontiguousarray(np.tile(tile, reps)[:h, :w]), texel
    albedo = np.asarray(tex.albedo, dtype=np.float32)
    img = np.empty((h, w, 3), dtype=np.float32)
    img[:] = albedo
    rng = np.random.default_rng([int(tex.seed) & 0xFFFFFFFF, key])
    u = ((np.arange(w, dtype=np.float64) + 0.5) * texel).astype(np.float32)
    v = ((np.arange(h, dtype=np.float64) + 0.5) * texel).astype(np.float32)

    def add_noise(octaves: tuple[tuple[float, float], ...]) -> None:
        for cell_1, amp in octaves:
            cell = cell_1 * s
            if cell < 2.0 * texel:
                continue
            grid = rng.uniform(-1.0, 1.0, (math.ceil(height_m / cell) + 4, math.ceil(width_m / cell) + 4, 3))
            map_x = np.ascontiguousarray(np.broadcast_to(u[None, :] / cell + 1.0, (h, w)), dtype=np.float32)
            map_y = np.ascontiguousarray(np.broadcast_to(v[:, None] / cell + 1.0, (h, w)), dtype=np.float32)
            img[:] += amp * cv2.remap(
                grid.astype(np.float32), map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
            )

    add_noise(_COARSE_NOISE)
    canvas = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    _draw_shapes(canvas, rng, albedo, width_m * height_m, s, texel)
    img = canvas.astype(np.float32) / 255.0
    add_noise(_FINE_NOISE)
    np.clip(img, 0.0, 1.0, out=img)
    return img, texel


def _periodic_tile(tex: Texture, texel: float, key: int) -> np.ndarray:
    """One period of a periodic pattern, a whole number of texels a side (so that it repeats exactly). [h, w, 3]

    The tile's colours (the albedo, a joint colour and a motif colour) and a faint speckle inside it come from the
    texture's seed: every period is identical, speckle included.
    """
    s = float(tex.scale)
    pw, ph = (max(4, round(m * s / texel)) for m in _PERIOD[tex.pattern])
    joint = max(1, round(_JOINT * s / texel))
    rng = np.random.default_rng([int(tex.seed) & 0xFFFFFFFF, key, 11])
    albedo = np.asarray(tex.albedo, dtype=np.float64)
    line = tuple(int(c) for c in np.clip(np.rint((0.35 * albedo + rng.uniform(0.0, 0.3, 3)) * 255), 0, 255))
    motif = tuple(int(c) for c in np.clip(np.rint(rng.uniform(0.05, 0.95, 3) * 255), 0, 255))
    speckle = rng.uniform(-0.05, 0.05, (ph, pw, 1))
    tile = np.clip(np.rint((albedo + speckle) * 255), 0, 255).astype(np.uint8)  # [ph, pw, 3]
    if tex.pattern == "bricks":  # two courses; the second offset by half a brick
        half = ph // 2
        tile[:joint], tile[half : half + joint] = line, line
        tile[:half, :joint] = line
        tile[half:, pw // 2 : pw // 2 + joint] = line
    elif tex.pattern == "tiles":  # grout on two sides and one motif (a disc and a bar) per tile
        tile[:joint], tile[:, :joint] = line, line
        centre, radius = (pw // 2 * 16, ph // 2 * 16), int(0.22 * min(pw, ph) * 16)
        cv2.circle(tile, centre, radius, motif, -1, cv2.LINE_AA, 4)
        bar = np.array([[0.3 * pw, 0.75 * ph], [0.7 * pw, 0.75 * ph], [0.7 * pw, 0.82 * ph], [0.3 * pw, 0.82 * ph]])
        cv2.fillPoly(tile, [np.rint(bar * 16).astype(np.int32)], motif, cv2.LINE_AA, 4)
    elif tex.pattern == "grid":
        tile[:joint], tile[:, :joint] = line, line
    else:
        raise AssertionError(tex.pattern)
    return tile.astype(np.float32) / 255.0


def _bilinear(img: np.ndarray, texel: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``img`` at surface coordinates in metres (clamped at the border). [M] → [M, 3]"""
    h, w = img.shape[:2]
    x = np.clip(u * (1.0 / texel) - 0.5, 0.0, w - 1.0)
    y = np.clip(v * (1.0 / texel) - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.intp), w - 2)
    y0 = np.minimum(y.astype(np.intp), h - 2)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    flat = img.reshape(-1, 3)
    i00 = y0 * w + x0
    c00, c01, c10, c11 = flat[i00], flat[i00 + 1], flat[i00 + w], flat[i00 + w + 1]
    top = c00 + (c01 - c00) * fx
    bottom = c10 + (c11 - c10) * fx
    return top + (bottom - top) * fy


def _sample(
    tex: Texture, cache: dict, key: int, width_m: float, height_m: float, u: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """Texture colour at ``(u, v)`` metres on a ``width_m × height_m`` surface (rasterised once, cached). [M, 3]"""
    if not tex.textured:
        return np.broadcast_to(np.asarray(tex.albedo, dtype=np.float32), (len(u), 3))
    if ("tex", key) not in cache:
        cache[("tex", key)] = _shared_texture(tex, width_m, height_m, key)
    img, texel = cache[("tex", key)]
    return _bilinear(img, texel, u, v)


_SHARED: OrderedDict[tuple[Texture, float, float, int], tuple[np.ndarray, float]] = OrderedDict()
_SHARED_LOCK = threading.Lock()


def _shared_texture(tex: Texture, width_m: float, height_m: float, key: int) -> tuple[np.ndarray, float]:
    """:func:`_texture_image`, through the process-wide cache (the image read-only: it is shared)."""
    k = (tex, width_m, height_m, key)
    with _SHARED_LOCK:
        if k in _SHARED:
            _SHARED.move_to_end(k)
            return _SHARED[k]
    img, texel = _texture_image(tex, width_m, height_m, key)
    img.flags.writeable = False
    with _SHARED_LOCK:
        _SHARED[k] = (img, texel)
        total = sum(v[0].nbytes for v in _SHARED.values())
        while total > SHARED_CACHE_BYTES and len(_SHARED) > 1:
            total -= _SHARED.popitem(last=False)[1][0].nbytes
    return img, texel
