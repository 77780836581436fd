"""Training recipes: the values of every setting of ``macsplat train`` that decides what is reproduced, each recipe a
named :class:`~.config.TrainConfig` (as hloc's named confs).

* ``paper`` (default): what the MAC-Splat paper states — AdamW at 1e-5, ``L = L_photo + 0.25 · L_MAC`` with
  λp = 1, λs = 0.02, λa = 0.1, the L1 sums and one normaliser of its equations, ``w = c(f'₁)·c(f'₂)`` — and
  macsplat's choices where it is silent (256×192 frames, 2 targets, batch 2, warm-up + cosine, LPIPS 0.25 as
  Splatt3R, Huber δ 0.01 / 0.1). One addition of macsplat's: the match weights carry the dual-softmax
  probability ``p`` (``c0c1p``), without which no loss reaches the fusion module the paper says it trains.
* ``released-code``: what the authors' released training code computes (GitHub ``Jinqianyang/MAC-SPLAT``; the
  point-by-point comparison is ``models/mac-splat.md``) — Adam at 1e-6, ×0.1 at half the steps, batch 1,
  512×512 frames cut around the principal point, 3 targets, masked MSE ÷ (3 · mask pixels) + 0.1 · masked LPIPS,
  0.2 · MAC with its means, δ 0.05 and clamps, reciprocal matches over all pixels from stride-8 seeds,
  ``c = 1 + exp(x)`` weights on at most 4096 of them, scales capped
  at 0.5, samples drawn scene first, 10 epochs of 20 samples per scene — **except its bugs**
  (:data:`RELEASED_CODE_BUGS`, written to ``run.json`` with what this recipe does instead) and the parts macsplat
  does not rebuild (:data:`RELEASED_CODE_NOT_REPRODUCED`).

Options given on the command line override a recipe's values (``run.json`` records the values used, and which
options overrode them).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import InputError
from ..mac import MACConfig
from .config import TrainConfig
from .loss import LossConfig

__all__ = [
    "RECIPES",
    "RELEASED_CODE_BUGS",
    "RELEASED_CODE_NOT_REPRODUCED",
    "get_recipe",
    "recipe_record",
]


def _paper(out: Path) -> TrainConfig:
    return TrainConfig(out=out, recipe="paper")  # TrainConfig's defaults are the paper's values


def _released_code(out: Path) -> TrainConfig:
    mac = MACConfig(
        lambda_pos=1.0, lambda_shape=0.02, lambda_app=0.1, delta_pos=0.05, delta_shape=0.05, reduction="mean",
        clamp_pos=1.0, clamp_shape=1.0, clamp_opacity=1.0, clamp_colour=2.0, weight=0.2,
    )  # fmt: skip
    loss = LossConfig(
        lpips_weight=0.1, mac_weight=0.2, mac=mac, mac_weighting="c0c1", conf_floor=1.0, max_matches=4096,
        photo_reduction="mask", matcher="seeded", seed_stride=8, seed_iters=10, near_plane=0.1,
    )  # fmt: skip
    return TrainConfig(
        out=out, recipe="released-code", optimizer="adam", lr=1e-6, weight_decay=0.0, schedule="step", warmup=0,
        lr_drop_at=0.5, lr_drop=0.1, grad_clip=0.5, batch=1, steps_per_scene=10 * 20, size=(512, 512),
        crop="principal-point", targets=3, loss=loss, max_scale=0.5, exclude_scenes=("303745abc7", "cc5237fd77"),
        per_scene=20,
    )  # fmt: skip


RECIPES: dict[str, Callable[[Path], TrainConfig]] = {"paper": _paper, "released-code": _released_code}
"""Recipe name → a fresh :class:`~.config.TrainConfig` of its values for a run folder (its loss config is
mutable)."""

RELEASED_CODE_BUGS: dict[str, str] = {
    "B1": "view 2's Gaussians (in camera 1's frame) are moved by camera 2's pose in the MAC position term: here both "
    "views go through context 0's pose, as the paper's equation",
    "B2": "the MAC denominator adds the confidence sum once per active term (about 4x): here one denominator, "
    "sum(w) + eps",
    "B3": "the gate (w >= 0.05 on (1+e^x)(1+e^x') >= 1) removes nothing: here the weights keep 1+e^x and the gate "
    "is macsplat's e^x * e^x' > 1 (the paper's w > tau)",
    "B4": "the fusion MLP is randomly initialised and gets no gradient (a fixed random change to the descriptors and "
    "their confidences): here macsplat's zero-initialised fusion, which with c0c1 weights gets no gradient either "
    "and stays the identity",
    "B5": "DINOv3 ViT-L/16 is loaded strict=False into a plain ViT (no RoPE, registers or LayerScale; random position "
    "embedding): here DINOv3 as released, loaded strictly",
    "B6": "the masked SSIM is 3x the mean (a sum over 3 channels over the mask's pixel count): here the mean",
    "B7": "the scale regulariser runs under no_grad (a constant; left out), the config's weight_decay 0.1 never "
    "reaches Adam (here Adam without decay: what it computes), the chunk size is read at the wrong config level "
    "(no chunking here)",
    "B8": "all_reduce without a process group (a 1-GPU run fails) and DINOv3 load errors swallowed: here reductions "
    "only under torchrun, and load errors stop the run",
}
"""The release's bugs (``models/mac-splat.md``), each with what ``--recipe released-code`` does instead."""

RELEASED_CODE_NOT_REPRODUCED: tuple[str, ...] = (
    "sampling: both draw a scene, a first context, then a second among its partners (scenes x 20 samples an epoch); "
    "the release's first context is any frame (with fallbacks to the best overlap when none is in range), here a "
    "frame with a partner in --coverage",
    "fusion: the release's 2816->3200->6400 token MLP per view is not built (inert there: B4); macsplat's "
    "descriptor-level fusion stands in",
)
"""Differences of ``--recipe released-code`` from the release that are not bugs, named in ``run.json``."""


def get_recipe(name: str, out: Path) -> TrainConfig:
    """A fresh config of the named recipe for the run folder ``out``. Raises :class:`~macsplat_cli.errors.InputError`
    for an unknown one."""
    try:
        return RECIPES[name](out)
    except KeyError:
        raise InputError(f"--recipe {name!r}: use {' or '.join(RECIPES)}") from None


def recipe_record(config: TrainConfig, overridden: list[str]) -> dict[str, Any]:
    """What ``run.json`` says of the recipe (its values are the run's ``config``): its name, the options that
    overrode them, and for ``released-code`` each omitted bug and each part not reproduced."""
    out: dict[str, Any] = {"name": config.recipe, "overridden": overridden}
    if config.recipe == "released-code":
        out["omitted_bugs"] = dict(RELEASED_CODE_BUGS)
        out["not_reproduced"] = list(RELEASED_CODE_NOT_REPRODUCED)
    return out
