"""SSIM's separable blur and the precomputed target (:func:`~macsplat_cli.metrics.ssim_target`) against the 2-D
11 × 11 window it replaces: values and gradients, float64 and float32, and ``ssim()``'s evaluation figures."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from macsplat_cli.metrics import SsimTarget, ssim, ssim_map, ssim_target


def _window(size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _ssim_map_2d(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """The form before the separable blur: five 2-D ``window × window`` convolutions. [H, W, C] → [H', W']"""
    p, t = pred.permute(2, 0, 1)[None], target.to(pred.dtype).permute(2, 0, 1)[None]
    c = p.shape[1]
    g = _window(window, sigma, pred.dtype)
    k = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, k, groups=c)

    mu_p, mu_t = blur(p), blur(t)
    s_pp, s_tt, s_pt = blur(p * p) - mu_p**2, blur(t * t) - mu_t**2, blur(p * t) - mu_p * mu_t
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu_p * mu_t + c1) * (2 * s_pt + c2)) / ((mu_p**2 + mu_t**2 + c1) * (s_pp + s_tt + c2)))[0].mean(0)


def _pair(seed: int, h: int = 40, w: int = 56, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, ...]:
    """A photo and a noisy render of it, in [0, 1]. [h, w, 3] each"""
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(h, w, 3, generator=g, dtype=dtype)
    return (t + 0.1 * torch.randn(h, w, 3, generator=g, dtype=dtype)).clamp(0, 1), t


@pytest.mark.parametrize("precomputed", [False, True])
def test_separable_ssim_equals_the_2d_window_with_its_gradient(precomputed: bool) -> None:
    pred, target = _pair(0)
    weights = torch.rand(30, 46, dtype=torch.float64)
    a, b = pred.clone().requires_grad_(True), pred.clone().requires_grad_(True)
    new = ssim_map(a, ssim_target(target) if precomputed else target)
    old = _ssim_map_2d(b, target)
    (new * weights).sum().backward()
    (old * weights).sum().backward()
    assert new.shape == old.shape == (30, 46)
    # float64: the two forms differ by rounding only (~1e-15 here); the brief's bound is 1e-6
    assert float((new - old).detach().abs().max()) <= 1e-12
    assert a.grad is not None and b.grad is not None
    assert float((a.grad - b.grad).abs().max()) <= 1e-12


def test_separable_ssim_in_float32_is_no_less_accurate_than_the_2d_window() -> None:
    for seed in range(3):
        pred, target = _pair(seed, 64, 80)
        truth = _ssim_map_2d(pred, target)
        err_new = float((ssim_map(pred.float(), target.float()).double() - truth).abs().max())
        err_old = float((_ssim_map_2d(pred.float(), target.float()).double() - truth).abs().max())
        assert err_new <= err_old, (seed, err_new, err_old)


def test_precomputed_target_gives_the_same_map_bit_for_bit() -> None:
    pred, target = _pair(1, dtype=torch.float32)
    st = ssim_target(target)
    assert isinstance(st, SsimTarget) and st.mu.shape == st.var.shape == (1, 3, 30, 46)
    assert torch.equal(ssim_map(pred, st), ssim_map(pred, target))
    with pytest.raises(ValueError, match="window 7"):
        ssim_map(pred, st, window=7)


def test_ssim_target_passes_a_gradient_to_a_target_that_wants_one() -> None:
    pred, target = _pair(2, 12, 12)
    inputs = (pred.requires_grad_(True), target.requires_grad_(True))
    assert torch.autograd.gradcheck(lambda p, t: ssim_map(p, t, window=5), inputs)


def test_ssim_score_matches_the_2d_window() -> None:
    pred, target = _pair(3, 48, 64)
    assert ssim(pred.numpy(), target.numpy()) == pytest.approx(float(_ssim_map_2d(pred, target).mean()), abs=1e-12)
