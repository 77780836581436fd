"""The masked image metrics of the evaluation against hand-computed values on tiny images: PSNR over the mask in
both conventions (per channel; summed over the channels), and LPIPS over the mask (the per-pixel map's masked mean)
with random LPIPS weights in the official layouts."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.evaluation.metrics import image_metrics
from macsplat_cli.lpips import load_lpips

U = 2.0**-24
"""float32's unit roundoff."""


def test_masked_psnr_both_formulas_by_hand() -> None:
    t = np.zeros((16, 16, 3))  # (the SSIM window needs 11 pixels)
    p = t.copy()
    p[0, 0] = (0.1, 0.2, 0.3)  # inside the mask
    p[3, 3] = (0.5, 0.5, 0.5)  # outside: ignored by both masked formulas
    mask = np.zeros((16, 16), bool)
    mask[:2, :2] = True  # 4 pixels
    m = image_metrics(p, t, mask)
    sq = 0.1**2 + 0.2**2 + 0.3**2  # 0.14, the one pixel's squared error summed over the channels
    assert m["psnr_masked"] == pytest.approx(-10 * math.log10(sq / (3 * 4)), abs=1e-9)  # Σerr² / (3 · mask px)
    assert m["psnr_masked_rgbsum"] == pytest.approx(-10 * math.log10(sq / 4), abs=1e-9)  # Σerr² / mask px
    assert m["psnr_masked"] - m["psnr_masked_rgbsum"] == pytest.approx(10 * math.log10(3), abs=1e-9)
    assert m["psnr"] == pytest.approx(-10 * math.log10((sq + 0.75) / 768), abs=1e-9)  # the whole image


@pytest.fixture(scope="module")
def lpips(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    g = torch.Generator().manual_seed(0)
    convs = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256), (12, 256, 256),
             (14, 256, 256), (17, 256, 512), (19, 512, 512), (21, 512, 512), (24, 512, 512), (26, 512, 512),
             (28, 512, 512)]  # fmt: skip
    vgg = {}
    for idx, cin, cout in convs:
        vgg[f"features.{idx}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * (2.0 / (9 * cin)) ** 0.5
        vgg[f"features.{idx}.bias"] = torch.randn(cout, generator=g) * 0.01
    lin = {
        f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for k, c in enumerate([64, 128, 256, 512, 512])
    }
    folder: Path = tmp_path_factory.mktemp("lpips")
    torch.save(vgg, folder / "vgg16-397923af.pth")
    torch.save(lin, folder / "vgg.pth")
    return load_lpips(folder)


def _rtol(n: int) -> float:
    """Two float32 reductions of the same n non-negative terms (the lin weights are positive) in different orders,
    after a bilinear upsampling whose weights (¾, ¼) are exact: each side within (⌈log₂ n⌉ + 8)·u of the exact sum
    (pairwise summation, the five taps' additions, the upsampling's two roundings), both sides together twice that."""
    return 2 * (math.ceil(math.log2(n)) + 8) * U


def test_masked_lpips_is_the_per_pixel_maps_masked_mean(lpips) -> None:  # noqa: ANN001
    g = torch.Generator().manual_seed(3)
    h, w = 32, 48  # multiples of 16: the upsampled maps keep each tap's mean
    t = torch.rand(h, w, 3, generator=g).double().numpy()
    p = np.clip(t + 0.1 * torch.randn(h, w, 3, generator=g).double().numpy(), 0, 1)
    full = np.ones((h, w), bool)
    m = image_metrics(p, t, full, lpips=lpips)
    assert m["lpips_masked"] == pytest.approx(m["lpips"], rel=_rtol(h * w), abs=0)  # the whole mask: the same distance
    half = np.zeros((h, w), bool)
    half[:, : w // 2] = True
    m = image_metrics(p, t, half, lpips=lpips)
    pm, tm = (torch.from_numpy((a * half[..., None]).astype(np.float32)) for a in (p, t))
    dmap = lpips.spatial(pm, tm).double().numpy()
    assert m["lpips_masked"] == pytest.approx(float(dmap[half].mean()), rel=0, abs=0)  # the masked images' map
    assert m["lpips_masked"] != pytest.approx(float(dmap.mean()), rel=1e-3)  # … averaged over the mask only
    assert m["lpips"] == pytest.approx(float(lpips(torch.from_numpy(p.astype(np.float32)),
                                                   torch.from_numpy(t.astype(np.float32)))), rel=0, abs=0)  # fmt: skip
