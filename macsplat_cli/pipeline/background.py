"""The unseen region: a far layer of large Gaussians around both photos, so that a novel view never shows an empty band.

A target camera between or beside the two inputs sees past the edge of both photos; with only the per-pixel
Gaussians that region renders as the flat background colour (black by default), which costs more PSNR on the
development scenes than any depth error. For each view this module extends the photo beyond its borders on a
coarse grid (``cell`` working pixels, ``margin`` of the image size on every side) and places one large, nearly
opaque Gaussian per grid cell:

* colour: the photo extended past its border (border replicated, then low-passed at the cell scale, so a wall or
  floor continues with its colour rather than its texture);
* depth: the view's inverse depth extended the same way (push-pull from the border pixels), never nearer than
  the view's median depth: a wrong far layer only reads as background, a wrong near one hides the scene;
* shape: a disc facing the camera, std ``overlap`` grid steps, so the cells tile without gaps.

Cells whose centre falls inside the other photo are left out (that view has real Gaussians there, and a layer at
an extrapolated depth could hide them). With ``behind`` the interior of each photo gets the same layer pushed
``behind_factor`` beyond the farthest depth of the cell: a pixel that both views leave uncovered in a novel view
(a disocclusion) then shows the far surface's blurred colour instead of the background colour (twice the farthest
depth by default; measured: benchmarks/history/depth.md). With three photos or more, a behind cell that another photo
sees through (its depth there lies beyond the cell: the cell would hide a surface that photo saw, from every viewpoint
near it) is left out too (:data:`SEEN_THROUGH`).

The layer is returned as a flat :class:`~macsplat_cli.gaussians.Gaussians` set in the world (camera-0) frame,
apart from the per-pixel maps; it is not refined or compacted.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..gaussians import Gaussians
from ..rotations import rotmat_to_quat_np
from .depth import push_pull
from .types import DepthMap, TwoViewGeometry, View

__all__ = ["BackgroundConfig", "BackgroundLayer", "background_gaussians", "background_layer"]

logger = logging.getLogger(__name__)

MARGIN = 0.6
"""How far the far layer extends past each image border, as a fraction of the image's width / height."""
CELL = 16
"""Grid step of the layer, in working pixels."""
OVERLAP = 0.65
"""Gaussian std in grid steps (≥ 0.5 leaves no gap between cells)."""
OPACITY = 0.99
"""Opacity of the layer's Gaussians."""
BEHIND_FACTOR = 2.0
"""The interior layer's depth relative to the farthest depth in its cell."""
SEEN_THROUGH = 1.05
"""A behind cell is dropped where another photo's depth at the cell's projection exceeds the cell's depth in that
photo by this factor (that photo sees a surface behind it). Two photos 12-30° apart rarely see past an object's cells
at twice its depth; eight photos over 45° do, and their behind discs cost the views between the middle photos 1.3 dB
(benchmarks/history/multiview_joint.md)."""
SEEN_THROUGH_MIN_VIEWS = 3
"""The seen-through rule applies from this many photos: on the dev pairs it measured −0.24 … +0.22 dB (mean −0.01),
so two-photo scenes keep their layer as it was."""


@dataclass
class BackgroundConfig:
    """Args:
    enabled: build the far layer (off: regions no photo saw render as the renderer's background colour).
    behind: also put a layer behind each photo's interior (fills disocclusions with the far colour).
    """

    enabled: bool = True
    behind: bool = True


@dataclass
class BackgroundLayer:
    """The far layer and how many Gaussians each rule placed.

    Attributes:
        gaussians: the layer in the world (camera-0) frame (``None`` when disabled or empty).
        counts: rule → Gaussians placed (``outside_view{k}``: past view k's border; ``behind_view{k}``: behind its
            interior), and ``dropped_inside_other``: cells left out because the other photo covers them.
    """

    gaussians: Gaussians | None
    counts: dict[str, int]


def _extend(values: np.ndarray, weights: np.ndarray, pad: tuple[int, int]) -> np.ndarray:
    """``values`` [h, w, C] (one per grid cell) on a grid padded by ``pad = (py, px)`` cells per side: known cells
    kept, the rest pulled from them (push-pull), then low-passed over about one cell. [h + 2py, w + 2px, C]"""
    py, px = pad
    h, w = values.shape[:2]
    canvas = np.zeros((h + 2 * py, w + 2 * px, values.shape[2]), np.float32)
    wc = np.zeros(canvas.shape[:2], np.float32)
    canvas[py : py + h, px : px + w] = values
    wc[py : py + h, px : px + w] = weights
    out = np.stack([push_pull(canvas[..., c], wc) for c in range(values.shape[2])], -1)
    blurred = cv2.GaussianBlur(out, (0, 0), 1.0).reshape(out.shape)
    known = (wc > 0)[..., None]
    return np.where(known, out, blurred)


def _cell_min(values: np.ndarray, cell: int, fill: float) -> np.ndarray:
    """Smallest value in each ``cell``×``cell`` block (partial blocks at the far edges included).
    [⌈H/c⌉, ⌈W/c⌉]"""
    h, w = values.shape
    hc, wc = -(-h // cell), -(-w // cell)
    padded = np.full((hc * cell, wc * cell), fill, np.float32)
    padded[:h, :w] = values
    return padded.reshape(hc, cell, wc, cell).min((1, 3))


def background_gaussians(
    views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap], config: BackgroundConfig | None = None
) -> BackgroundLayer:
    """The far layer of both views (module docstring), in the world frame.

    Args:
        views: the two working views.
        geometry: their poses and intrinsics.
        depths: their depth maps (working resolution); pixels without a depth are ignored.

    Returns:
        The layer and its counts.
    """
    Ks = [geometry.K0, geometry.K1]
    return background_layer(views, Ks, [geometry.cam_to_world(k) for k in (0, 1)], depths, config)


def background_layer(
    views: Sequence[View], Ks: Sequence[np.ndarray], poses: Sequence[np.ndarray], depths: Sequence[DepthMap],
    config: BackgroundConfig | None = None,
) -> BackgroundLayer:  # fmt: skip
    """The far layer of any number of views (module docstring): each view's cells, less the exterior cells another
    view sees. ``Ks`` [3, 3] and ``poses`` (cam_to_world [4, 4]) per view, at the working resolution."""
    cfg = config or BackgroundConfig()
    counts: dict[str, int] = {}
    if not cfg.enabled:
        return BackgroundLayer(None, counts)
    parts: list[_ViewLayer] = []
    dropped = 0
    for k, (view, dm) in enumerate(zip(views, depths)):
        if not dm.valid.any():
            continue
        others = [(Ks[o], poses[o], depths[o]) for o in range(len(views)) if o != k]
        part = _view_layer(view, dm, Ks[k], poses[k], others, cfg, through=len(views) >= SEEN_THROUGH_MIN_VIEWS)
        counts[f"outside_view{k}"] = part.outside
        counts[f"behind_view{k}"] = part.behind
        dropped += part.dropped
        parts.append(part)
    counts["dropped_inside_other"] = dropped
    if not parts:
        return BackgroundLayer(None, counts)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(np.concatenate(a), np.float32))  # noqa: E731
    n = sum(len(p.means) for p in parts)
    means, scales, quats = t([p.means for p in parts]), t([p.scales for p in parts]), t([p.quats for p in parts])
    colours = t([p.colours for p in parts]).clamp(0, 1)
    g = Gaussians.from_activated(means, scales, quats, torch.full((n,), OPACITY), colours)
    logger.debug("background layer: %s", counts)
    return BackgroundLayer(g, counts)


@dataclass
class _ViewLayer:
    """One view's part of the far layer (camera-0 frame) and its counts.

    Attributes:
        means: centres. [n, 3]
        scales: standard deviations (a disc facing the view's camera). [n, 3]
        colours: RGB. [n, 3]
        quats: (w, x, y, z), the camera's axes. [n, 4]
        outside: Gaussians past the view's border; behind: behind its interior; dropped: exterior cells the other
            photo covers, left out.
    """

    means: np.ndarray
    scales: np.ndarray
    colours: np.ndarray
    quats: np.ndarray
    outside: int
    behind: int
    dropped: int


_Other = tuple[np.ndarray, np.ndarray, DepthMap]
"""Another view: its ``K`` [3, 3], cam_to_world [4, 4] and depth map (working resolution)."""


def _view_layer(
    view: View, dm: DepthMap, K: np.ndarray, T: np.ndarray, others: Sequence[_Other], cfg: BackgroundConfig,
    *, through: bool = False,
) -> _ViewLayer:  # fmt: skip
    """A view's cells (intrinsics ``K``, cam_to_world ``T``): the photo and its depth extended on the padded grid,
    placed in the world, less the exterior cells another view sees (and, with ``through``, the behind cells another
    view sees past)."""
    h, w = dm.depth.shape
    valid = dm.valid
    cell = max(2, int(CELL))
    hc, wc = -(-h // cell), -(-w // cell)
    py, px = int(np.ceil(MARGIN * hc)), int(np.ceil(MARGIN * wc))
    col, inv_ext, inv, z_med = _extended_cells(view, dm.depth, valid, (hc, wc), (py, px))
    gy, gx = np.mgrid[0 : hc + 2 * py, 0 : wc + 2 * px]
    u = (gx - px + 0.5) * (w / wc)  # working-image pixel coordinates (+0.5 centres) of the cell centres
    v = (gy - py + 0.5) * (h / hc)
    inside = (gx >= px) & (gx < px + wc) & (gy >= py) & (gy < py + hc)
    z = np.maximum(1.0 / np.maximum(inv_ext, 1e-12), z_med)
    if cfg.behind:
        far = _cell_min(np.where(valid, inv, np.inf).astype(np.float32), cell, np.inf)[:hc, :wc]
        far = np.where(np.isfinite(far), far, 1.0 / z_med)
        z_far = np.zeros_like(z)
        z_far[py : py + hc, px : px + wc] = BEHIND_FACTOR / np.maximum(far, 1e-12)
        z = np.where(inside, np.maximum(z_far, z), z)
        keep = np.ones_like(inside)
    else:
        keep = ~inside
    rays = np.stack([u, v, np.ones_like(u, dtype=np.float64)], -1) @ np.linalg.inv(K).T
    Pw = (rays * z[..., None]) @ T[:3, :3].T + T[:3, 3]
    # leave out exterior cells another photo sees: its own Gaussians are there
    seen = np.zeros(Pw.shape[:-1], bool)
    through_any = np.zeros(Pw.shape[:-1], bool)  # behind cells another photo sees past
    for K_o, T_o, dm_o in others:
        inside_o, uv_o, z_o = _project_into(Pw, K_o, T_o, dm_o.depth.shape)
        seen |= inside_o
        if cfg.behind and through:
            through_any |= _sees_past(inside_o, uv_o, z_o, dm_o)
    outside_kept = keep & ~inside & ~seen
    sel = outside_kept | (keep & inside & ~through_any)
    f = 0.5 * (K[0, 0] + K[1, 1])
    s = OVERLAP * cell * z[sel] / f
    return _ViewLayer(
        means=Pw[sel],
        scales=np.stack([s, s, 0.1 * s], 1),
        colours=col[sel],
        # a disc facing camera k: its local axes are the camera's axes
        quats=np.repeat(rotmat_to_quat_np(T[None, :3, :3]), int(sel.sum()), 0),
        outside=int(outside_kept.sum()),
        behind=int((keep & inside & ~through_any).sum()),
        dropped=int((keep & ~inside & seen).sum()),
    )


def _extended_cells(
    view: View, depth: np.ndarray, valid: np.ndarray, grid: tuple[int, int], pad: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The photo's colour and inverse depth per grid cell (``grid = (hc, wc)`` cells over the [H, W] ``depth``),
    extended by ``pad = (py, px)`` cells per side (:func:`_extend`).

    Returns:
        ``(colour, inverse depth, the working inverse depth, the median depth)``: [hc + 2py, wc + 2px, 3],
        [hc + 2py, wc + 2px], [H, W] (0 where no depth), and a float.
    """
    h, w = depth.shape
    hc, wc = grid
    img = view.image.astype(np.float32)
    if img.shape[:2] != (h, w):
        img = np.asarray(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
    inv = np.where(valid, 1.0 / np.maximum(depth, 1e-12), 0.0).astype(np.float32)
    z_med = float(np.median(depth[valid]))
    img_c = cv2.resize(img, (wc, hc), interpolation=cv2.INTER_AREA).reshape(hc, wc, 3)
    vw = cv2.resize(valid.astype(np.float32), (wc, hc), interpolation=cv2.INTER_AREA)
    iw = cv2.resize(inv, (wc, hc), interpolation=cv2.INTER_AREA)
    inv_c = np.where(vw > 0, iw / np.maximum(vw, 1e-6), 0.0).astype(np.float32)
    col = _extend(img_c, np.ones((hc, wc), np.float32), pad)
    inv_ext = _extend(inv_c[..., None], vw, pad)[..., 0]
    return col, inv_ext, inv, z_med


def _project_into(
    Pw: np.ndarray, K_o: np.ndarray, T_o: np.ndarray, shape_o: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [..., 3] in a view (``K_o``, cam_to_world ``T_o``, ``shape_o = (height, width)``): whether each
    lands inside its image in front of it [...] bool, its pixel [..., 2] and its depth there [...]."""
    To = np.linalg.inv(T_o)
    Po = Pw @ To[:3, :3].T + To[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvo = (Po @ K_o.T)[..., :2] / Po[..., 2:3]
    ho, wo = shape_o
    inside = (Po[..., 2] > 0) & (uvo[..., 0] > 0) & (uvo[..., 0] < wo) & (uvo[..., 1] > 0) & (uvo[..., 1] < ho)
    return inside, uvo, Po[..., 2]


def _sees_past(inside: np.ndarray, uv: np.ndarray, z: np.ndarray, dm: DepthMap) -> np.ndarray:
    """Of points projected into a view (:func:`_project_into`), those its depth map ``dm`` sees past: a valid depth
    more than :data:`SEEN_THROUGH` times the point's own there. [...] bool"""
    col = np.where(inside, uv[..., 0], 0).astype(np.int64)
    row = np.where(inside, uv[..., 1], 0).astype(np.int64)
    return inside & dm.valid[row, col] & (dm.depth[row, col] > SEEN_THROUGH * z)
