"""Where view-dependent colour is allowed: the Numba kernel against its PyTorch twin (issue 40: the joint
refinement's set-up at 32 photos)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.gaussians import GaussianMaps
from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig, view_gaussians
from macsplat_cli.pipeline.multiview import sh_views
from macsplat_cli.pipeline.types import DepthMap, View

W, H = 64, 48


@pytest.fixture(scope="module")
def photos() -> tuple[list[GaussianMaps], list[np.ndarray]]:
    """Six photos of a textured room over 30° (every spread case: points seen by 1 to 6 photos, pairs both sides of
    the 10° spread), their exact depths' Gaussians and intrinsics; one photo a little closer, so its depths differ."""
    scene = syn.make_scene("room", 2)
    angles = [-15.0, -9.0, -3.0, 3.0, 9.0, 15.0]
    cams = syn.orbit_cameras(scene, angles, width=W, height=H, fov_deg=60.0, names=[f"v{k}" for k in range(6)])
    ref = np.linalg.inv(cams[0].cam_to_world)
    maps, Ks = [], []
    for k, c in enumerate(cams):
        T = ref @ c.cam_to_world
        if k == 4:
            T[:3, 3] *= 0.97
        r = syn.render(scene, c, supersample=1)
        d = r.depth.astype(np.float32)
        v = View(c.name, Path(c.name), r.image.astype(np.float32), np.ones((H, W), bool), c.K.copy(), (W, H), "file")
        maps.append(view_gaussians(v, DepthMap(d, (d > 0).astype(np.float32)), v.K, T, GaussianInitConfig()))
        Ks.append(c.K.copy())
    return maps, Ks


def test_the_kernel_allows_what_its_pytorch_twin_allows(photos: tuple) -> None:
    """Every valid Gaussian gets the twin's answer (the kernel sums its matrix products in its own order: a point on
    a pixel edge or on the depth tolerance may round the other way, at most one in ten thousand), with every case
    present: allowed, seen by too few photos, seen by enough but from too narrow an angle."""
    maps, Ks = photos
    got, ref = sh_views.view_dependent(maps, Ks), sh_views.view_dependent_reference(maps, Ks)
    valid = sum(int(m.valid_mask().sum()) for m in maps)
    differ = sum(int((g != r).sum()) for g, r in zip(got, ref))
    assert differ <= max(1, valid // 10_000), (differ, valid)
    allowed = sum(int(g.sum()) for g in got)
    assert 0.05 * valid < allowed < 0.95 * valid, (allowed, valid)
    assert all(not bool((g & ~m.valid_mask()).any()) for g, m in zip(got, maps))  # only valid Gaussians
    narrow = sh_views.view_dependent([maps[2], maps[3], maps[2]], [Ks[2], Ks[3], Ks[2]])  # seen 3 times, 6° apart
    assert not any(bool(g.any()) for g in narrow)


def test_the_kernel_splits_into_chunks_without_changing_a_bit(photos: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """One kernel thread or two: the same masks (each point is computed alone)."""
    from macsplat_cli import _threads

    maps, Ks = photos
    two = sh_views.view_dependent(maps, Ks)
    monkeypatch.setattr(_threads, "kernel_threads", lambda: 1)
    one = sh_views.view_dependent(maps, Ks)
    assert all(torch.equal(a, b) for a, b in zip(one, two))
