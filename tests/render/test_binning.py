"""Tile binning (render/_kernels.bin_tiles) against its definition: tile t lists, in increasing index order, every
Gaussian whose rectangle touches it."""

from __future__ import annotations

import numpy as np
import pytest

from macsplat_cli.render import _kernels


def _by_definition(rect: np.ndarray, width: int, height: int, tile: int) -> list[list[int]]:
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    out: list[list[int]] = [[] for _ in range(tiles_x * tiles_y)]
    for g, (x0, x1, y0, y1) in enumerate(rect.tolist()):
        for ty in range(y0 // tile, y1 // tile + 1):
            for tx in range(x0 // tile, x1 // tile + 1):
                out[ty * tiles_x + tx].append(g)
    return out


@pytest.mark.parametrize(("m", "width", "height"), [(0, 32, 32), (7, 40, 30), (70_000, 333, 250)])
def test_bin_tiles_matches_its_definition(m: int, width: int, height: int) -> None:
    """70 000 Gaussians: the binning splits them into runs, one thread a run (``_BIN_MIN_RUN``)."""
    rng = np.random.default_rng(m)
    x0, y0 = rng.integers(0, width, m), rng.integers(0, height, m)
    x1 = np.minimum(x0 + rng.integers(0, 50, m), width - 1)
    y1 = np.minimum(y0 + rng.integers(0, 50, m), height - 1)
    rect = np.ascontiguousarray(np.stack([x0, x1, y0, y1], 1).astype(np.int32))
    assert m < 2 * _kernels._BIN_MIN_RUN or m // _kernels._BIN_MIN_RUN >= 2, "the big case must use several runs"
    offsets, lists = _kernels.bin_tiles(rect, width, height, 16)
    want = _by_definition(rect, width, height, 16)
    assert offsets.tolist() == np.cumsum([0] + [len(t) for t in want]).tolist()
    assert lists.tolist() == [g for t in want for g in t]
