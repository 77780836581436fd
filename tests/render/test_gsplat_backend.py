"""The optional gsplat CUDA path. No GPU is available in CI, so a fake ``gsplat`` module
records the call: this checks the conventions macsplat passes (OpenCV view matrix, pixel
K, activations, dilation, near plane) and how it assembles the outputs."""

from __future__ import annotations

import sys
import types

import pytest
import torch

from macsplat_cli.errors import InputError
from macsplat_cli.render import _gsplat, render

from support.gaussians import pinhole, random_gaussians


def test_gsplat_arguments_and_outputs(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {}

    def rasterization(**kw):  # noqa: ANN003, ANN202
        calls.update(kw)
        h, w = kw["height"], kw["width"]
        n = kw["means"].shape[0]
        colors = torch.zeros(1, h, w, 4)
        colors[..., :3] = 0.25
        colors[..., 3] = 1.5  # accumulated depth: Σ w z
        alphas = torch.full((1, h, w, 1), 0.5)
        radii = torch.zeros(1, n, 2, dtype=torch.int32)
        radii[0, :3] = 2
        return colors, alphas, {"radii": radii, "means2d": torch.zeros(1, n, 2), "n_isects": 42}

    monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=rasterization))
    g = random_gaussians(10, sh_degree=2)
    g.means[4, 0] = float("nan")  # non-finite Gaussians never reach gsplat
    V = torch.eye(4)
    V[:3, 3] = torch.tensor([0.1, 0.2, 0.3])
    K = pinhole(16, 12)
    monkeypatch.setattr(_gsplat, "_require_cuda", lambda g: None)  # CPU tensors stand in for CUDA ones
    out = _gsplat.render_gsplat(g, V, K, 16, 12, torch.tensor([1.0, 0.0, 0.0]), near=0.01, far=1e10, eps2d=0.3)
    assert calls["means"].shape[0] == 9
    assert torch.equal(calls["viewmats"][0], V) and torch.equal(calls["Ks"][0], K)
    assert calls["eps2d"] == 0.3 and calls["near_plane"] == 0.01 and calls["sh_degree"] == 2
    keep = torch.tensor([i for i in range(10) if i != 4])
    # exp and sigmoid of the same numbers, possibly another memory layout: ≤ 1 ulp (2u) and ≤ 2 ulps a side
    u = torch.finfo(torch.float32).eps / 2
    assert torch.allclose(calls["scales"], g.scales[keep], rtol=4 * u, atol=0)
    assert torch.allclose(calls["opacities"], g.opacities[keep], rtol=8 * u, atol=0)
    assert torch.equal(calls["colors"], g.sh[keep])
    assert calls["render_mode"] == "RGB+D"
    # 0.25 + (1 − 0.5)·bg and 1.5/0.5: binary-exact operands, exact results
    assert torch.equal(out.rgb, torch.tensor([0.25 + 0.5, 0.25, 0.25]).expand(12, 16, 3))  # + (1 − α)·bg
    assert torch.equal(out.depth, torch.full((12, 16), 3.0))  # Σ w z / α
    assert out.visible.tolist() == [0, 1, 2] and out.n_intersections == 42


def test_gsplat_backend_needs_cuda_tensors() -> None:
    g = random_gaussians(5)
    if _gsplat.available():  # pragma: no cover - a machine with CUDA and gsplat
        pytest.skip("CUDA present")
    with pytest.raises(InputError):
        render(g, torch.eye(4), pinhole(8, 8), 8, 8, backend="gsplat")


def test_auto_backend_uses_cpu_kernels_on_cpu() -> None:
    g = random_gaussians(50)
    a = render(g, torch.eye(4), pinhole(16, 16), 16, 16, backend="auto")
    b = render(g, torch.eye(4), pinhole(16, 16), 16, 16, backend="numba")
    assert torch.equal(a.rgb, b.rgb) and a.n_intersections == b.n_intersections > 0
