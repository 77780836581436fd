"""LPIPS-VGG from user-supplied weights: loading the official layouts, the metric's properties,
and an independent functional computation of the same network."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from macsplat_cli.lpips import LPIPS, LPIPSWeightsError, load_lpips

from support.numerics import forward_rel_tol, forward_rel_tol_probabilistic

CONVS = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256), (12, 256, 256), (14, 256, 256),
         (17, 256, 512), (19, 512, 512), (21, 512, 512), (24, 512, 512), (26, 512, 512), (28, 512, 512)]  # fmt: skip


def _official(seed: int = 0) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Random weights in torchvision's VGG16 layout (with its classifier) and LPIPS v0.1's."""
    g = torch.Generator().manual_seed(seed)
    vgg = {}
    for idx, cin, cout in CONVS:
        vgg[f"features.{idx}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * (2.0 / (9 * cin)) ** 0.5
        vgg[f"features.{idx}.bias"] = torch.randn(cout, generator=g) * 0.01
    vgg["classifier.0.weight"] = torch.zeros(8, 4)  # ignored (the real one is 4096 × 25088)
    lin = {
        f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for k, c in enumerate([64, 128, 256, 512, 512])
    }
    return vgg, lin


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, dict]:
    folder = tmp_path_factory.mktemp("lpips")
    vgg, lin = _official()
    torch.save(vgg, folder / "vgg16-397923af.pth")
    torch.save(lin, folder / "vgg.pth")
    return folder, vgg, lin


def _reference(x: torch.Tensor, y: torch.Tensor, vgg: dict, lin: dict) -> torch.Tensor:
    """LPIPS written out with functional calls: scaling, 13 convolutions, 4 pools, 5 taps."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).reshape(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).reshape(1, 3, 1, 1)
    feats = []
    for img in (x, y):
        h = ((img * 2 - 1) - shift) / scale
        taps = []
        for idx, _, _ in CONVS:
            if idx in (5, 10, 17, 24):
                h = F.max_pool2d(h, 2)
            h = F.relu(F.conv2d(h, vgg[f"features.{idx}.weight"], vgg[f"features.{idx}.bias"], padding=1))
            if idx in (2, 7, 14, 21, 28):
                taps.append(h)
        feats.append(taps)
    d = 0.0
    for k, (a, b) in enumerate(zip(*feats)):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        d = d + ((a - b) ** 2 * lin[f"lin{k}.model.1.weight"]).sum(1).mean(dim=(1, 2))
    return d


def _lpips_rtol(model: LPIPS, d: float) -> float:
    """Relative tolerance between two float32 evaluations of the LPIPS distance ``d`` in different orders (batched
    or not): the unit feature vectors are off by ε, so â − b̂ by 2ε and the squared difference by 4ε/‖â − b̂‖
    relative, with ‖â − b̂‖ ≈ √(2d/5) (d sums 5 taps of ½·‖â − b̂‖², the lin weights averaging ½); two evaluations.
    ε from the 13 convolutions (fan-in 27 … 4608): the worst case Σγ(n) is 2.1e-3 (``forward_rel_tol``), which
    would allow 3–15 % here, too loose to catch a wrong term; the probabilistic Σ8√n·u is 2.9e-4."""
    assert forward_rel_tol(model) > 2e-3  # the worst case named above
    eps = forward_rel_tol_probabilistic(model)
    return 2 * 4 * eps / math.sqrt(2 * d / 5)


def test_matches_a_functional_computation(weights: tuple[Path, dict, dict]) -> None:
    folder, vgg, lin = weights
    model = load_lpips(folder)
    g = torch.Generator().manual_seed(1)
    x, y = torch.rand(2, 3, 48, 64, generator=g), torch.rand(2, 3, 48, 64, generator=g)
    # (b) the model runs the pair as one batch, the reference image by image (measured: equal bits)
    ref = _reference(x, y, vgg, lin)
    torch.testing.assert_close(model(x, y), ref, rtol=_lpips_rtol(model, float(ref.min())), atol=0)


def test_metric_properties(weights: tuple[Path, dict, dict]) -> None:
    model = load_lpips(weights[0])
    g = torch.Generator().manual_seed(2)
    x = torch.rand(32, 40, 3, generator=g)
    y = (x + 0.05 * torch.randn(32, 40, 3, generator=g)).clamp(0, 1)
    z = torch.rand(32, 40, 3, generator=g)
    assert float(model(x, x)) == 0.0  # (a) both images run in one batch through the same kernels: â = b̂ exactly
    # (b) the swapped pair puts each image in the other batch slot; (â − b̂)² is symmetric exactly (measured: equal
    # bits)
    d = float(model(x, y))
    assert float(model(y, x)) == pytest.approx(d, rel=_lpips_rtol(model, d), abs=0)
    assert 0 < d < float(model(x, z))  # a small perturbation is closer than another image
    # (a) an HWC image is permuted to the same [1, 3, H, W] view as the test's, then concatenated (copied): the same
    # numbers in the same layout through the same kernels
    assert torch.equal(model(x, y), model(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None])[0])
    pred = y.clone().requires_grad_(True)
    model(pred, x).backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    assert not any(p.requires_grad for p in model.parameters())
    model.train()
    assert not model.training


def test_single_file_with_both_key_sets(weights: tuple[Path, dict, dict], tmp_path: Path) -> None:
    _, vgg, lin = weights
    torch.save({**vgg, **lin}, tmp_path / "lpips_vgg.pth")
    x, y = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
    # (a) the same weights into the same modules, the same input: the same kernels on the same numbers
    assert torch.equal(load_lpips(tmp_path / "lpips_vgg.pth")(x, y), load_lpips(weights[0])(x, y))


def test_bad_weights_name_the_problem(weights: tuple[Path, dict, dict], tmp_path: Path) -> None:
    _, vgg, lin = weights
    with pytest.raises(LPIPSWeightsError, match="no such file"):
        load_lpips(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(LPIPSWeightsError, match="vgg16"):
        load_lpips(tmp_path / "empty")
    bad = {**vgg, **lin, "lin2.model.1.weight": torch.rand(1, 128, 1, 1)}
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(
        LPIPSWeightsError, match=r"'lin2.model.1.weight' has shape \[1, 128, 1, 1\] in the file but shape \[1, 256"
    ) as e:
        load_lpips(tmp_path / "bad.pth")
    assert e.value.key == "lin2.model.1.weight"
    assert (e.value.file_shape, e.value.model_shape) == ((1, 128, 1, 1), (1, 256, 1, 1))
    torch.save(vgg, tmp_path / "vgg_only.pth")
    with pytest.raises(LPIPSWeightsError, match="lin0.model.1.weight") as e:
        load_lpips(tmp_path / "vgg_only.pth")
    assert e.value.file_shape is None and e.value.model_shape == (1, 64, 1, 1)
    assert e.value.missing_keys == tuple(f"lin{k}.model.1.weight" for k in range(5))
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(LPIPSWeightsError, match="not a readable"):
        load_lpips(tmp_path / "junk.pth")
    with pytest.raises(Exception, match="shapes differ"):
        LPIPS()(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 16))
