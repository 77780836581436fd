"""The Multi-Attribute Consistency (MAC) loss of MAC-Splat.

Matched pixels of two views should predict the same Gaussian. For each match ``k`` with
joint confidence ``w_k``, the Gaussians at its two pixels (bilinearly sampled from the
per-pixel parameter maps) are compared in world space:

* position: ``L_pos = Huber_δ(‖μ¹ − μ²‖₁)``, with ``μ = R·μ_cam + t``, only where both
  camera-space depths are positive (the L1 norm, as the paper defines it, is invariant to
  translating the world but not to rotating it);
* shape: ``L_shape = Huber_δs(‖log λ(Σ¹) − log λ(Σ²)‖₁)``, the eigenvalues of the world
  covariances sorted. Eigenvalues are rotation-invariant, so with the scale/rotation
  parameterisation they are the squared scales and ``log λ = 2·log s`` — no
  eigendecomposition, whose gradient is undefined for the repeated eigenvalues of
  isotropic Gaussians. Raw covariances use ``torch.linalg.eigvalsh``: its gradient,
  ``V·diag(ḡ)·Vᵀ``, stays finite and correct for repeated eigenvalues (only
  *eigenvector* gradients divide by eigenvalue gaps), and its values are accurate to
  ~1e-16·‖Σ‖ (a trigonometric closed form loses accuracy near repeated roots; measured:
  benchmarks/history/refine.md). No method resolves eigenvalues below ~1e-16·‖Σ‖ from a
  covariance's entries, so prefer scales and rotations for very flat Gaussians;
* appearance: ``L_app = |α¹ − α²| + ‖c¹ − c²‖₁`` (opacity and all SH coefficients; the maps hold
  opacity logits, and ``α = sigmoid(logit)`` is taken per pixel before sampling).

``L_MAC = Σ_k w_k (λp·L_pos + λs·L_shape + λa·L_app) / (Σ_k w_k + ε)``, defaults
``λp = 1``, ``λs = 0.02``, ``λa = 0.1``; the total training/refinement loss adds
``λ_MAC = 0.25`` times it. With no matches, or all weights zero, the loss is exactly 0
with zero gradients.

Huber: ``Huber_δ(x) = x²/(2δ)`` for ``x < δ``, else ``x − δ/2`` (the smooth-L1 form, so the
tail has unit slope). ``δ = 0.01`` scene units for positions (1 % of the baseline in a
relative-scale reconstruction, about 1 cm in a metric one), ``δs = 0.1`` for shapes (a 10 %
difference of a standard deviation).

**The release's form** (``reduction="mean"`` and the clamps; ``macsplat train --recipe released-code``): the
MAC-Splat authors' code averages where the paper sums — the position L1 over x, y, z (``‖Δμ‖₁/3``), the shape
over the three log standard deviations (``‖Δ log λ‖₁/6``, as ``log σ = ½ log λ``), the colour over the SH
coefficients — and clamps each match's terms (Huber'd position and shape at 1, opacity at 1, colour at 2). The
default is the paper's form, unclamped.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ._checks import check_finite, check_shape
from .errors import InputError
from .gaussians import GaussianMaps

__all__ = ["MACConfig", "MACLoss", "huber", "mac_loss", "sample_maps"]


@dataclass
class MACConfig:
    """Weights of the MAC loss (defaults from the paper) and its Huber thresholds.

    Args:
        lambda_pos: weight of the position term λp.
        lambda_shape: weight of the shape term λs.
        lambda_app: weight of the appearance term λa.
        delta_pos: Huber threshold of the position term, scene units.
        delta_shape: Huber threshold of the shape term, log units.
        eps: added to the weight sum.
        weight: λ_MAC, the MAC loss's weight in the total loss.
        reduction: ``"sum"`` (the paper's L1 norms) or ``"mean"`` (the release's means: module docstring).
        clamp_pos: each match's Huber'd position term is at most this (None: no clamp; the release: 1).
        clamp_shape: the same for the shape term (the release: 1).
        clamp_opacity: the same for the opacity difference (the release: 1, which an opacity in [0, 1] never
            reaches).
        clamp_colour: the same for the colour difference (the release: 2).
    """

    lambda_pos: float = 1.0
    lambda_shape: float = 0.02
    lambda_app: float = 0.1
    delta_pos: float = 0.01
    delta_shape: float = 0.1
    eps: float = 1e-6
    weight: float = 0.25
    reduction: str = "sum"
    clamp_pos: float | None = None
    clamp_shape: float | None = None
    clamp_opacity: float | None = None
    clamp_colour: float | None = None

    def __post_init__(self) -> None:
        if self.reduction not in ("sum", "mean"):
            raise InputError(f"MAC reduction {self.reduction!r}: use sum or mean")


def _clamped(x: torch.Tensor, bound: float | None) -> torch.Tensor:
    return x if bound is None else x.clamp(max=bound)


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """``x²/(2δ)`` for ``|x| < δ``, else ``|x| − δ/2``. Elementwise."""
    a = x.abs()
    return torch.where(a < delta, 0.5 * a * a / delta, a - 0.5 * delta)


def sample_maps(maps: torch.Tensor, xy: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample per-pixel values at continuous pixel positions.

    Args:
        maps: values per pixel. [B, H, W, C]
        xy: positions in pixels, pixel centres at +0.5 (so ``align_corners=False``). [M, 2]
        batch: which map each position samples. [M] int64

    Returns:
        The sampled values (borders clamp). [M, C]
    """
    b, h, w, c = maps.shape
    out = maps.new_zeros((xy.shape[0], c))
    if xy.shape[0] == 0:
        return out + 0.0 * maps.sum()  # keep the graph: exactly-zero gradients, not None
    grid = torch.stack([2.0 * xy[:, 0] / w - 1.0, 2.0 * xy[:, 1] / h - 1.0], dim=-1).to(maps.dtype)
    pieces = []
    for bi in torch.unique(batch).tolist():
        sel = (batch == bi).nonzero().squeeze(1)
        g = grid[sel].view(1, 1, -1, 2)
        v = F.grid_sample(
            maps[bi : bi + 1].permute(0, 3, 1, 2), g, mode="bilinear", padding_mode="border", align_corners=False
        )  # [1, C, 1, m]
        pieces.append((sel, v[0, :, 0].T))
    for sel, v in pieces:
        out = out.index_copy(0, sel, v)
    return out


def _log_eigs(
    maps: GaussianMaps, cov: torch.Tensor | None, xy: torch.Tensor, batch: torch.Tensor, R: torch.Tensor
) -> torch.Tensor:
    """Sorted log-eigenvalues of the world covariances at the match pixels. [M, 3]

    From ``maps.log_scales``, or from ``cov`` (camera-frame covariances ``[B, H, W, 3, 3]``) when given.
    """
    if cov is None:
        ls = sample_maps(maps.log_scales, xy, batch)
        return torch.sort(2.0 * ls, dim=-1).values  # λ = s², rotation-invariant
    b, h, w = cov.shape[:3]
    c = sample_maps(cov.reshape(b, h, w, 9), xy, batch).reshape(-1, 3, 3)
    cov_w = R @ c @ R.transpose(-1, -2)
    lam = torch.linalg.eigvalsh(0.5 * (cov_w + cov_w.transpose(-1, -2)))  # ascending
    return torch.log(lam.clamp_min(torch.finfo(lam.dtype).tiny))


@dataclass
class MACLoss:
    """The loss and its weighted terms (each term is its confidence-weighted mean)."""

    loss: torch.Tensor
    position: torch.Tensor
    shape: torch.Tensor
    appearance: torch.Tensor
    matches: int


def mac_loss(
    view1: GaussianMaps,
    view2: GaussianMaps,
    xy1: torch.Tensor,  # [M, 2]
    xy2: torch.Tensor,  # [M, 2]
    batch: torch.Tensor,  # [M]
    weights: torch.Tensor,  # [M]
    cam_to_world1: torch.Tensor | None = None,  # [B, 4, 4]
    cam_to_world2: torch.Tensor | None = None,  # [B, 4, 4]
    config: MACConfig | None = None,
    *,
    covariances: tuple[torch.Tensor | None, torch.Tensor | None] | None = None,
    check_inputs: bool = True,
) -> MACLoss:
    """Multi-Attribute Consistency loss between two views' Gaussian maps.

    Args:
        view1: per-pixel Gaussians of the first view of each pair (opacity logits). [B, H1, W1, ·]
        view2: per-pixel Gaussians of the second view. [B, H2, W2, ·]
        xy1: match pixels in view 1 (pixel centres at +0.5). [M, 2]
        xy2: match pixels in view 2. [M, 2]
        batch: pair index of each match. [M] int64
        weights: joint confidence ``w = c1·c2`` of each match, ≥ 0. [M]
        cam_to_world1: camera-to-world transforms of view 1; None: ``view1.cam_to_world`` (cast
            to the maps' dtype), or the identity if that is None too. [B, 4, 4]
        cam_to_world2: the same for view 2. [B, 4, 4]
        config: weights and Huber thresholds.
        covariances: raw camera-frame covariances of view 1 and view 2, used by the shape term
            instead of that view's log-scales (the quaternions are never used); None for a view:
            its log-scales. ([B, H1, W1, 3, 3], [B, H2, W2, 3, 3])
        check_inputs: validate shapes and finiteness (NaN/Inf raise
            :class:`~macsplat_cli.errors.NonFiniteError`).

    Returns:
        :class:`MACLoss`: ``loss`` (to be multiplied by ``config.weight`` in a total loss)
        and its three weighted terms.
    """
    cfg = config or MACConfig()
    # the transforms to use: the given ones, else the maps' own (in their dtype), else the identity
    cam_to_world1 = cam_to_world1 if cam_to_world1 is not None else view1.cam_to_world_or_identity(view1.dtype)
    cam_to_world2 = cam_to_world2 if cam_to_world2 is not None else view2.cam_to_world_or_identity(view2.dtype)
    cov1, cov2 = covariances if covariances is not None else (None, None)
    if check_inputs:
        _check_inputs(view1, view2, xy1, xy2, batch, weights, (cam_to_world1, cam_to_world2), (cov1, cov2))
    batch = batch.long()
    R1, t1 = cam_to_world1[batch, :3, :3], cam_to_world1[batch, :3, 3]
    R2, t2 = cam_to_world2[batch, :3, :3], cam_to_world2[batch, :3, 3]

    mu1c = sample_maps(view1.means, xy1, batch)
    mu2c = sample_maps(view2.means, xy2, batch)
    mu1 = (R1 @ mu1c[..., None])[..., 0] + t1
    mu2 = (R2 @ mu2c[..., None])[..., 0] + t2
    in_front = ((mu1c[:, 2] > 0) & (mu2c[:, 2] > 0)).to(mu1.dtype)
    mean = cfg.reduction == "mean"
    d_pos = (mu1 - mu2).abs()
    l_pos = _clamped(huber(d_pos.mean(-1) if mean else d_pos.sum(-1), cfg.delta_pos), cfg.clamp_pos) * in_front

    d_log = (_log_eigs(view1, cov1, xy1, batch, R1) - _log_eigs(view2, cov2, xy2, batch, R2)).abs()
    l_shape = _clamped(huber(0.5 * d_log.mean(-1) if mean else d_log.sum(-1), cfg.delta_shape), cfg.clamp_shape)

    a1 = sample_maps(torch.sigmoid(view1.opacity_logits)[..., None], xy1, batch)[:, 0]
    a2 = sample_maps(torch.sigmoid(view2.opacity_logits)[..., None], xy2, batch)[:, 0]
    b, h, w = view1.sh.shape[:3]
    c1 = sample_maps(view1.sh.reshape(b, h, w, -1), xy1, batch)
    b2, h2, w2 = view2.sh.shape[:3]
    c2 = sample_maps(view2.sh.reshape(b2, h2, w2, -1), xy2, batch)
    d_col = (c1 - c2).abs()
    l_app = _clamped((a1 - a2).abs(), cfg.clamp_opacity) + _clamped(
        d_col.mean(-1) if mean else d_col.sum(-1), cfg.clamp_colour
    )

    wt = weights.to(mu1.dtype)
    norm = wt.sum() + cfg.eps
    pos, shape, app = (wt * l_pos).sum() / norm, (wt * l_shape).sum() / norm, (wt * l_app).sum() / norm
    loss = cfg.lambda_pos * pos + cfg.lambda_shape * shape + cfg.lambda_app * app
    return MACLoss(loss=loss, position=pos, shape=shape, appearance=app, matches=int(xy1.shape[0]))


def _check_inputs(
    view1: GaussianMaps, view2: GaussianMaps, xy1: torch.Tensor, xy2: torch.Tensor, batch: torch.Tensor,
    weights: torch.Tensor, cam_to_world: tuple[torch.Tensor, torch.Tensor],
    covariances: tuple[torch.Tensor | None, torch.Tensor | None],
) -> None:  # fmt: skip
    """:func:`mac_loss`'s ``check_inputs``: shapes, finiteness, weights ≥ 0 and batch indices in range."""
    cam_to_world1, cam_to_world2 = cam_to_world
    cov1, cov2 = covariances
    check_shape(xy1, ("M", 2), "xy1")
    m = xy1.shape[0]
    check_shape(xy2, (m, 2), "xy2")
    check_shape(batch, (m,), "batch")
    check_shape(weights, (m,), "weights")
    bsz = view1.means.shape[0]
    check_shape(cam_to_world1, (bsz, 4, 4), "cam_to_world1")
    check_shape(cam_to_world2, (bsz, 4, 4), "cam_to_world2")
    if view2.means.shape[0] != bsz:
        raise InputError(f"view1 has {bsz} maps but view2 has {view2.means.shape[0]}")
    for name, t in (("xy1", xy1), ("xy2", xy2), ("weights", weights)):
        check_finite(t, name)
    check_finite(cam_to_world1, "cam_to_world1")
    check_finite(cam_to_world2, "cam_to_world2")
    view1.check_finite()
    view2.check_finite()
    for name, cov, maps in (("covariances[0]", cov1, view1), ("covariances[1]", cov2, view2)):
        if cov is not None:
            check_shape(cov, (bsz, *maps.size, 3, 3), name)
            check_finite(cov, name)
    if m and (bool((weights < 0).any()) or int(batch.min()) < 0 or int(batch.max()) >= bsz):
        raise InputError("match weights must be ≥ 0 and batch indices within the batch")
