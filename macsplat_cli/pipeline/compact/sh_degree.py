"""The compaction's SH step: the lowest SH degree whose colours match the full degree's from the views."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ...gaussians import Gaussians
from ...sh import eval_sh, num_sh_bases
from .config import CompactConfig
from .state import ViewState

__all__ = ["quantile", "sh_degree", "sh_photo_check"]

SAMPLES = 200_000
"""Gaussians whose colours are compared (a deterministic subsample beyond it): plenty for a 95th percentile."""
QUANTILE_MAX = 2**24
"""The most values ``torch.quantile`` accepts; the Gaussians compared shrink so that Gaussians × eyes stays within it
(the eyes grow as N(N + 1)/2 with N photos: 136 at 16 photos)."""


def quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    """``torch.quantile(x, q)`` (linear interpolation) of a 1-D floating tensor, from its two order statistics
    (``kthvalue``, linear time) instead of a full sort: the same ranks, weight and ``lerp`` in ``x``'s dtype, so the
    same bits (``tests/pipeline/test_compact.py``); 2²⁴ values take 0.27 s instead of 2.4. NaN if ``x`` holds one,
    as ``torch.quantile``. ``x``: [M], M ≥ 1."""
    if bool(torch.isnan(x).any()):
        return torch.tensor(float("nan"), dtype=x.dtype)
    ranks = torch.tensor(q, dtype=x.dtype) * (x.numel() - 1)
    below, above = int(ranks.long()), int(ranks.ceil().long())
    low = x.kthvalue(below + 1).values
    high = low if above == below else x.kthvalue(above + 1).values
    return torch.lerp(low, high, ranks - below)


def sh_degree(g: Gaussians, cams: list[ViewState], cfg: CompactConfig) -> tuple[int, str]:
    """The SH degree to keep, and why, from the view dependence of ``g``'s colours."""
    full = g.sh_degree
    if full == 0:
        return 0, "degree 0 already"
    if len(g) == 0:
        return 0, "no Gaussians"
    if cfg.sh == "keep":
        return full, "kept (sh='keep')"
    if cfg.sh == "zero":
        nonzero = [d for d in range(1, full + 1) if g.sh[:, num_sh_bases(d - 1) : num_sh_bases(d)].abs().amax() > 0]
        deg = max(nonzero, default=0)
        return deg, f"bands above {deg} are exactly zero" if deg < full else "every band is used"
    centres = [c.c2w[:3, 3].to(g.dtype) for c in cams]
    eyes = centres + [0.5 * (a + b) for i, a in enumerate(centres) for b in centres[i + 1 :]]
    sh, means = g.sh, g.means
    most = min(SAMPLES, QUANTILE_MAX // len(eyes))
    if len(g) > most:  # a deterministic subsample is enough for a percentile
        sh, means = sh[:: len(g) // most + 1], means[:: len(g) // most + 1]
    # per eye, each lower degree's largest channel difference from the full degree's colour (kept per eye, not the
    # colours: the values are the same, held in a third of the memory and one eye's colours at a time)
    diffs: dict[int, list[torch.Tensor]] = {d: [] for d in range(full)}
    for e in eyes:
        dirs = F.normalize(means - e, dim=-1)
        ref = eval_sh(sh[:, : num_sh_bases(full)], dirs).clamp_min(0)
        for d in range(full):
            diffs[d].append((eval_sh(sh[:, : num_sh_bases(d)], dirs).clamp_min(0) - ref).abs().amax(-1))
    for d in range(full):
        diff = torch.cat(diffs[d])
        p95 = float(quantile(diff.float(), 0.95)) if diff.numel() else 0.0
        if p95 <= cfg.sh_tol:
            return d, f"degree {d} differs by ≤ {p95:.4f} (95th pct) from degree {full} across the views"
    return full, f"the view-dependent colour exceeds {cfg.sh_tol:.4f} below degree {full}"


def sh_photo_check(views: list[ViewState], full: int, deg: int, cfg: CompactConfig) -> tuple[int, str] | None:
    """With photos: raise ``deg`` while a higher degree lowers the mean colour error at the pixels by > sh_tol."""
    errs = []
    for d in range(full + 1):
        total, n = 0.0, 0
        for v in views:
            if v.image is None:
                return None
            sel = v.alive.reshape(-1)
            if not sel.any():
                continue
            X = v.world_means().reshape(-1, 3)[sel].to(v.sh.dtype)
            dirs = F.normalize(X - v.c2w[:3, 3].to(X.dtype), dim=-1)
            c = eval_sh(v.sh.reshape(-1, v.sh.shape[-2], 3)[sel][:, : num_sh_bases(d)], dirs).clamp(0, 1)
            total += float((c - v.image.reshape(-1, 3)[sel]).abs().mean(-1).sum())
            n += int(sel.sum())
        errs.append(total / max(n, 1))
    best = deg
    for d in range(deg + 1, full + 1):
        if errs[best] - errs[d] > cfg.sh_tol:
            best = d
    if best == deg:
        return None
    return best, f"degree {best} lowers the colour error at the photos' pixels from {errs[deg]:.4f} to {errs[best]:.4f}"
