"""Validation of ``macsplat train``: PSNR, SSIM (and LPIPS when given) of the rendered targets of held-out pairs.

Every target is rendered whole from the Gaussians the predictor makes of its pair, at its ground-truth camera
(:func:`~.loss.render_targets`), and compared with its photo; the figures are means over all targets.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import torch

from ..lpips import LPIPS
from ..metrics import psnr, ssim
from ..neural.predictor import PairPredictor, prediction_from_outputs
from .loss import render_targets

__all__ = ["validation_metrics"]


@torch.no_grad()
def validation_metrics(
    predictor: PairPredictor,
    loader: Iterable[dict[str, torch.Tensor]],
    *,
    device: torch.device,
    autocast: Callable[[], Any],
    background: tuple[float, float, float],
    lpips: LPIPS | None = None,
    near: float = 0.01,
) -> dict[str, float]:
    """Mean image metrics of the targets of every batch (of one pair) that ``loader`` gives.

    Args:
        predictor: the model, in eval mode.
        loader: batches of one pair (:func:`~.data.make_loader` with ``batch_size=1``).
        device: where the predictor runs.
        autocast: a new autocast context of the run's precision.
        background: colour behind the Gaussians (``LossConfig.background``).
        lpips: the LPIPS model, or None (no ``lpips`` key).
        near: the renders' near plane (``LossConfig.near_plane``).

    Returns:
        ``{"psnr", "ssim"}`` (and ``"lpips"``), means over the targets.
    """
    psnrs: list[float] = []
    ssims: list[float] = []
    lpipss: list[float] = []
    for batch in loader:
        ctx = batch["context"].to(device)
        with autocast():
            outputs = predictor(ctx[:, 0], ctx[:, 1])
        pred = prediction_from_outputs([o.float() for o in outputs])
        if pred.gaussians is None:
            raise ValueError("validation needs the Gaussian head's outputs")
        h, w = batch["target"].shape[-2:]
        rgb = render_targets(pred.gaussians, 0, batch["target_K"][0], batch["target_c2w"][0],
                             batch["context_c2w"][0, 0], (h, w), background, near)  # fmt: skip
        gt = batch["target"][0].to(rgb.device)
        for r, g in zip(rgb.clamp(0, 1), gt):
            psnrs.append(float(psnr(r.permute(1, 2, 0), g.permute(1, 2, 0))))
            ssims.append(float(ssim(r.permute(1, 2, 0), g.permute(1, 2, 0))))
        if lpips is not None:
            lpipss.extend(float(v) for v in lpips(rgb.clamp(0, 1), gt))
    out = {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims))}
    return {**out, "lpips": float(np.mean(lpipss))} if lpipss else out
