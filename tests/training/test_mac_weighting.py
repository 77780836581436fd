"""train --mac-weighting: c0·c1·p (the fusion learns through p) against the paper's plain c0·c1; the matchers."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from macsplat_cli.errors import InputError
from macsplat_cli.training.loss import LossConfig, sample_matches

from support.cli import run_cli


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(16, 16, 8, generator=g), dim=-1)
    desc = torch.stack([d, d]).requires_grad_(True)  # identical views: every grid pixel matches itself
    return desc, torch.full((2, 16, 16), 2.0)


def test_plain_weighting_is_c0_c1_and_reaches_no_descriptor() -> None:
    desc, conf = _pair()
    xy0, xy1, w = sample_matches(desc, conf, LossConfig(mac_weighting="c0c1"))
    assert len(w) > 10 and torch.equal(xy0, xy1)
    assert torch.equal(w, torch.full_like(w, 4.0)) and not w.requires_grad  # c0·c1, no path to the descriptors


def test_default_weighting_carries_the_match_probability_and_its_gradient() -> None:
    desc, conf = _pair()
    _, _, w = sample_matches(desc, conf, LossConfig())
    assert LossConfig().mac_weighting == "c0c1p"
    assert ((w > 0) & (w <= 4.0)).all() and w.requires_grad  # c0·c1·p with p the dual-softmax probability
    w.sum().backward()
    assert desc.grad is not None and desc.grad.abs().sum() > 0


def test_cli_refuses_an_unknown_weighting(tmp_path: Path) -> None:
    code, _, err = run_cli(["train", "--data", tmp_path, "--out", tmp_path / "run", "--model", "tiny", "--init",
                            "random", "--mac-weighting", "c0"])  # fmt: skip
    assert code == 2 and "--mac-weighting 'c0': use c0c1p or c0c1" in err


def test_seeded_matcher_lands_on_any_pixel_and_needs_plain_weights() -> None:
    """The release's matcher: from stride-8 seeds, reciprocal pairs over all pixels — a view shifted by 3 px is
    matched 3 px off the seed grid; it has no match probability, so only c0c1 weights go with it."""
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(16, 16, 8, generator=g), dim=-1)
    desc = torch.stack([d, torch.roll(d, 3, dims=1)])  # view 1 = view 0 moved 3 px right
    conf = torch.full((2, 16, 16), 2.0)
    config = LossConfig(matcher="seeded", mac_weighting="c0c1", conf_floor=1.0)
    xy0, xy1, w = sample_matches(desc, conf, config)
    assert len(xy0) >= 4 and torch.equal(xy1 - xy0, torch.tensor([3.0, 0.0]).expand_as(xy0))
    assert torch.equal(w, torch.full_like(w, 9.0))  # (1 + 2)·(1 + 2)
    assert set(((xy0[:, 0] - 0.5) % 8).tolist()) == {0.0}  # from the seeds (the seeds are their own matches)
    with pytest.raises(InputError, match="no match probability"):
        LossConfig(matcher="seeded")
