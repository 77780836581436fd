"""Islands of wrong depth removed before the fill (:func:`macsplat_cli.pipeline.depth.remove_speckles`)."""

from __future__ import annotations

import numpy as np
import pytest

from macsplat_cli.pipeline.depth import remove_speckles


def _slanted_plane(h: int = 80, w: int = 120) -> np.ndarray:
    """A floor seen at a grazing angle: depth 2 at the bottom row to 6 at the top, smooth. [h, w] float32"""
    rows = np.linspace(6.0, 2.0, h, dtype=np.float32)[:, None]
    return np.repeat(rows, w, axis=1)


def test_small_islands_go_large_regions_and_slopes_stay() -> None:
    depth = _slanted_plane()
    depth[10:15, 20:25] *= 1.5  # a 25-px patch of wrong matches, 50 % too far
    depth[40:43, 90:93] *= 0.7  # a 9-px patch, 30 % too near
    depth[50:75, 40:70] = 1.5  # a box in front of the floor, 750 px
    depth[0:4, 100:104] = 0.0  # no depth here (separates nothing: it is a hole)
    island = remove_speckles(depth, max_size=100, max_step=0.04)
    expect = np.zeros_like(island)
    expect[10:15, 20:25] = True
    expect[40:43, 90:93] = True
    np.testing.assert_array_equal(island, expect)
    # the floor changes depth by 1.6 % a row at the top: one region, nothing removed from it


def test_the_size_and_step_limits() -> None:
    depth = _slanted_plane()
    depth[10:15, 20:25] *= 1.5
    assert not remove_speckles(depth, max_size=20, max_step=0.04).any()  # 25 px > 20: a region, kept
    assert not remove_speckles(depth, max_size=100, max_step=0.6).any()  # a 50 % step still connects
    assert not remove_speckles(depth, max_size=0, max_step=0.04).any()  # off
    assert not remove_speckles(np.zeros((8, 8), np.float32), max_size=10, max_step=0.04).any()
    # a slope steeper than the step splits a floor into one-row bands, each small: islands, but with no other
    # measured depth around them nothing contradicts them, and they stay
    steep = np.repeat(np.geomspace(1.0, 4.0, 40, dtype=np.float32)[:, None], 10, axis=1)  # 3.6 % a row
    assert not remove_speckles(steep, max_size=50, max_step=0.02).any()
    # ... while the same bands next to a measured wall at another depth go (the wall contradicts them)
    beside = np.concatenate([steep, np.full((40, 30), 8.0, np.float32)], axis=1)
    gone = remove_speckles(beside, max_size=50, max_step=0.02, context=31)
    assert gone[:, :10].mean() > 0.9 and not gone[:, 10:].any()


def test_an_island_that_agrees_with_its_surroundings_across_a_hole_stays() -> None:
    depth = _slanted_plane()
    depth[28:42, 48:62] = 0.0  # a hole in the floor ...
    depth[33:37, 53:57] = _slanted_plane()[33:37, 53:57]  # ... with a 16-px island of the right depth in it
    depth[10:14, 20:24] = 0.0  # and one with an island 40 % too near
    depth[11:13, 21:23] = _slanted_plane()[11:13, 21:23] * 0.6
    gone = remove_speckles(depth, max_size=100, max_step=0.04)
    assert not gone[33:37, 53:57].any()
    assert gone[11:13, 21:23].all() and gone.sum() == 4


@pytest.mark.parametrize("shape", [(1, 1), (3, 200), (300, 2)])
def test_degenerate_shapes(shape: tuple[int, int]) -> None:
    depth = np.full(shape, 2.0, np.float32)
    for size in (depth.size, depth.size - 1):  # an island (nothing around it to contradict it) or a region
        assert not remove_speckles(depth, max_size=size, max_step=0.04).any()
    if depth.size > 2:  # a pixel 50 % off inside it is an island its neighbours contradict
        depth.reshape(-1)[depth.size // 2] = 3.0
        assert remove_speckles(depth, max_size=1, max_step=0.04).sum() == 1
