"""View ↔ network grid: where a view's working pixels land on the network's input.

Both views must reach the network at one size: view 0 as MASt3R's loader prepares a photo (aspect kept,
centre crop to multiples of 16: :meth:`ViewWarp.mast3r`), or at a fixed-size network's size; view 1 is
scaled to cover that size and centre-cropped (:meth:`ViewWarp.fit`); intrinsics are transformed
accordingly, outputs are sampled back onto each view's own pixels, and pixels cropped away get no depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["ViewWarp"]


@dataclass(frozen=True)
class ViewWarp:
    """Maps a view's working pixels onto the network input grid: ``u = x·sx − ox``, ``v = y·sy − oy``.

    Pixel centres at +0.5 on both grids (exact for per-axis scaling and integer crops).

    Attributes:
        view_size: (W, H) of the view.
        net_size: (W, H) of the network input.
        scale: (sx, sy).
        offset: (ox, oy), the crop's top-left corner in the scaled image.
    """

    view_size: tuple[int, int]
    net_size: tuple[int, int]
    scale: tuple[float, float] = (1.0, 1.0)
    offset: tuple[int, int] = (0, 0)

    @classmethod
    def fit(cls, view_size: tuple[int, int], net_size: tuple[int, int]) -> ViewWarp:
        """Scale the view to cover ``net_size`` (aspect kept up to rounding), then centre-crop."""
        (w, h), (wn, hn) = view_size, net_size
        if (w, h) == (wn, hn):
            return cls(view_size, net_size)
        s = max(wn / w, hn / h)
        wr, hr = max(wn, round(w * s)), max(hn, round(h * s))
        return cls(view_size, net_size, (wr / w, hr / h), ((wr - wn) // 2, (hr - hn) // 2))

    @classmethod
    def mast3r(cls, view_size: tuple[int, int], original_size: tuple[int, int], square: int | None = None) -> ViewWarp:
        """MASt3R's own input preprocessing for view 0: the photo resized with its aspect kept (the long side
        to the view's long side) and centre-cropped to multiples of 16 — a square result is cut to 4:3, as the
        512 checkpoints never saw squares; ``square``: the short side to ``square`` and a centre square crop
        (the 224 checkpoints). The working image is stretched by up to a few per cent to make both its sides
        multiples of 16; this warp undoes that stretch, so the network sees the photo's true aspect."""
        (w, h), (wo, ho) = view_size, original_size
        if square:
            s = square / min(wo, ho)
            ws, hs = max(square, round(wo * s)), max(square, round(ho * s))
            wn = hn = square
        else:
            s = max(w, h) / max(wo, ho)
            ws, hs = round(wo * s), round(ho * s)
            wn, hn = ws // 16 * 16, hs // 16 * 16
            if wn == hn:
                hn = wn * 3 // 4 // 16 * 16
        if min(wn, hn) < 16:  # a sliver: nothing to crop to; the working image as it is
            return cls(view_size, view_size)
        if (ws, hs) == (w, h) and (wn, hn) == (w, h):
            return cls(view_size, view_size)
        return cls(view_size, (wn, hn), (ws / w, hs / h), ((ws - wn) // 2, (hs - hn) // 2))

    @property
    def identity(self) -> bool:
        return self.view_size == self.net_size

    def to_net(self, xy: np.ndarray) -> np.ndarray:
        """View pixels → network pixels. [N, 2] → [N, 2]"""
        return xy * np.asarray(self.scale) - np.asarray(self.offset, np.float64)

    def from_net(self, uv: np.ndarray) -> np.ndarray:
        """Network pixels → view pixels. [N, 2] → [N, 2]"""
        return (uv + np.asarray(self.offset, np.float64)) / np.asarray(self.scale)

    def K_net(self, K: np.ndarray) -> np.ndarray:
        """The view's intrinsics on the network grid. [3, 3]"""
        out = np.array(K, dtype=np.float64)
        out[0] *= self.scale[0]
        out[1] *= self.scale[1]
        out[0, 2] -= self.offset[0]
        out[1, 2] -= self.offset[1]
        return out

    def image(self, img: np.ndarray) -> np.ndarray:
        """The view's image (or mask) resampled onto the network grid. [H, W, ...] → [Hn, Wn, ...]"""
        if self.identity:
            return img
        (w, h), (wn, hn) = self.view_size, self.net_size
        wr, hr = round(w * self.scale[0]), round(h * self.scale[1])
        if img.dtype == bool:
            r = cv2.resize(img.astype(np.uint8), (wr, hr), interpolation=cv2.INTER_NEAREST).astype(bool)
        else:
            r = cv2.resize(img, (wr, hr), interpolation=cv2.INTER_AREA if wr < w else cv2.INTER_CUBIC)
            r = np.clip(r, 0.0, 1.0)
        ox, oy = self.offset
        return np.ascontiguousarray(r[oy : oy + hn, ox : ox + wn])

    def sample(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A network-grid map read back at the view's pixels (nearest neighbour).

        Returns the map on the view's grid and the pixels that fall inside the network input.
        [Hn, Wn, ...] → ([H, W, ...], [H, W] bool)
        """
        (w, h), (wn, hn) = self.view_size, self.net_size
        if self.identity:
            return a, np.ones((h, w), bool)
        u = np.floor((np.arange(w) + 0.5) * self.scale[0] - self.offset[0]).astype(np.int64)
        v = np.floor((np.arange(h) + 0.5) * self.scale[1] - self.offset[1]).astype(np.int64)
        inside = ((v >= 0) & (v < hn))[:, None] & ((u >= 0) & (u < wn))[None, :]
        out = a[np.clip(v, 0, hn - 1)[:, None], np.clip(u, 0, wn - 1)[None, :]]
        return out, inside
