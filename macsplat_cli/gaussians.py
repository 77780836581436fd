"""The scene model: a set of 3D Gaussians in the standard 3DGS parameterisation.

Two containers, one parameterisation (the 3DGS PLY's: log-scales, (w, x, y, z) quaternions,
opacity logits, band-major SH):

* :class:`Gaussians`: a flat set ``[N, ·]`` in the world frame — the scene;
* :class:`GaussianMaps`: one Gaussian per pixel of ``B`` views ``[B, H, W, ·]``, each in its view's
  camera frame — what the prediction stage (classical or the neural Gaussian head) produces, what the
  MAC loss samples at match pixels and what refinement optimises. :meth:`GaussianMaps.to_gaussians`
  turns it into the scene.

Symbols used across macsplat: ``N`` Gaussians, ``K = (d + 1)²`` SH coefficients
per colour channel for SH degree ``d``; ``B`` views of ``H × W`` pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ._checks import check_finite, check_shape
from .errors import InputError, ShapeError
from .rotations import quat_multiply, quat_to_rotmat, rotmat_to_quat_np
from .sh import MAX_SH_DEGREE, rgb_to_sh0, sh_degree_from_bases

__all__ = ["GaussianMaps", "Gaussians"]


PARAMETERS = ("means", "log_scales", "quats", "opacity_logits", "sh")
"""The five Gaussian parameters, in field order, shared by :class:`Gaussians` and :class:`GaussianMaps`."""


class _Parameters:
    """What both Gaussian types derive from their five parameter fields."""

    means: torch.Tensor  # a field of each subclass (the first of PARAMETERS)

    def _named(self) -> list[tuple[str, torch.Tensor]]:
        return [(name, getattr(self, name)) for name in PARAMETERS]

    def tensors(self) -> list[torch.Tensor]:
        """The five parameter tensors, in field order (e.g. to hand to an optimiser)."""
        return [getattr(self, name) for name in PARAMETERS]

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device


@dataclass
class Gaussians(_Parameters):
    """Pre-activation Gaussian parameters, exactly as a standard 3DGS PLY stores them.

    Attributes:
        means: centres in world coordinates. [N, 3]
        log_scales: natural log of the standard deviation along each local axis. [N, 3]
        quats: rotations as (w, x, y, z) quaternions, not necessarily normalised. [N, 4]
        opacity_logits: opacity before the sigmoid. [N]
        sh: spherical-harmonic colour coefficients, band-major: ``sh[:, 0]`` is the DC
            term of R, G, B. [N, K, 3], K ∈ {1, 4, 9, 16}

    Construction checks shapes and dtypes (all tensors share one floating dtype and
    device) and raises :class:`~macsplat_cli.errors.ShapeError` on a mismatch.
    Finiteness is checked on request (:meth:`check_finite`), since renderers cull
    non-finite Gaussians themselves.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor

    def __post_init__(self) -> None:
        check_shape(self.means, ("N", 3), "means")
        n = self.means.shape[0]
        check_shape(self.log_scales, (n, 3), "log_scales")
        check_shape(self.quats, (n, 4), "quats")
        check_shape(self.opacity_logits, (n,), "opacity_logits")
        check_shape(self.sh, (n, "K", 3), "sh")
        _check_sh_and_dtypes(self._named(), "[N, K, 3] with K in {1, 4, 9, 16}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def empty(cls, sh_degree: int = 0, dtype: torch.dtype = torch.float32) -> Gaussians:
        """A set of zero Gaussians."""
        k = (sh_degree + 1) ** 2
        z = torch.zeros
        return cls(
            z(0, 3, dtype=dtype), z(0, 3, dtype=dtype), z(0, 4, dtype=dtype), z(0, dtype=dtype), z(0, k, 3, dtype=dtype)
        )

    @classmethod
    def from_activated(
        cls,
        means: torch.Tensor,  # [N, 3]
        scales: torch.Tensor,  # [N, 3]
        quats: torch.Tensor,  # [N, 4]
        opacities: torch.Tensor,  # [N]
        rgb: torch.Tensor,  # [N, 3]
        sh_degree: int = 0,
    ) -> Gaussians:
        """Build from activated values: positive scales, opacities in (0, 1), colours in [0, 1].

        Opacities are clamped to [1e-6, 1 - 1e-6] and scales to ≥ 1e-30 before the
        inverse activations, so the stored parameters are finite.
        """
        eps = 1e-6
        op = opacities.clamp(eps, 1.0 - eps)
        sh = torch.zeros(means.shape[0], (sh_degree + 1) ** 2, 3, dtype=means.dtype, device=means.device)
        sh[:, 0] = rgb_to_sh0(rgb)
        return cls(
            means=means,
            log_scales=torch.log(scales.clamp_min(1e-30)),
            quats=quats,
            opacity_logits=torch.log(op) - torch.log1p(-op),
            sh=sh,
        )

    @staticmethod
    def cat(parts: Sequence[Gaussians]) -> Gaussians:
        """Concatenate sets of Gaussians; the SH degree becomes the highest one (zero-padded)."""
        if not parts:
            raise ValueError("cat() needs at least one set of Gaussians")
        k = max(p.sh.shape[1] for p in parts)

        def pad(sh: torch.Tensor) -> torch.Tensor:
            return torch.nn.functional.pad(sh, (0, 0, 0, k - sh.shape[1]))

        return Gaussians(
            means=torch.cat([p.means for p in parts]),
            log_scales=torch.cat([p.log_scales for p in parts]),
            quats=torch.cat([p.quats for p in parts]),
            opacity_logits=torch.cat([p.opacity_logits for p in parts]),
            sh=torch.cat([pad(p.sh) for p in parts]),
        )

    # ------------------------------------------------------------------ properties
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def scales(self) -> torch.Tensor:
        """Standard deviations along the local axes, ``exp(log_scales)``. [N, 3]"""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """Opacities in (0, 1), ``sigmoid(opacity_logits)``. [N]"""
        return torch.sigmoid(self.opacity_logits)

    def rotations(self) -> torch.Tensor:
        """Rotation matrices of the normalised quaternions. [N, 3, 3]"""
        return quat_to_rotmat(self.quats)

    def covariances(self) -> torch.Tensor:
        """World covariances ``R S² Rᵀ``. [N, 3, 3]"""
        m = self.rotations() * self.scales[:, None, :]
        return m @ m.transpose(-1, -2)

    # ------------------------------------------------------------------ transforms

    def _map(self, fn) -> Gaussians:  # noqa: ANN001 - internal
        return Gaussians(*(fn(t) for t in self.tensors()))

    def to(self, *args, **kwargs) -> Gaussians:  # noqa: ANN002, ANN003 - mirrors Tensor.to
        return self._map(lambda t: t.to(*args, **kwargs))

    def detach(self) -> Gaussians:
        return self._map(torch.Tensor.detach)

    def clone(self) -> Gaussians:
        return self._map(torch.Tensor.clone)

    def __getitem__(self, index: torch.Tensor | slice) -> Gaussians:
        """Select Gaussians by boolean mask ``[N]``, index tensor or slice."""
        return self._map(lambda t: t[index])

    def finite_mask(self) -> torch.Tensor:
        """``True`` for Gaussians whose parameters are all finite. [N] bool"""
        mask = torch.ones(len(self), dtype=torch.bool, device=self.device)
        for _, t in self._named():
            fin = torch.isfinite(t)
            mask &= fin.flatten(1).all(1) if fin.dim() > 1 else fin
        return mask

    def check_finite(self) -> None:
        """Raise :class:`~macsplat_cli.errors.NonFiniteError` if any parameter is NaN or Inf."""
        for name, t in self._named():
            check_finite(t, name)


def _check_sh_and_dtypes(named: list[tuple[str, torch.Tensor]], sh_pattern: str) -> None:
    """SH size in {1, 4, 9, 16}; one floating dtype and one device for all parameters (``named[0]`` = means)."""
    sh = dict(named)["sh"]
    try:
        degree = sh_degree_from_bases(sh.shape[-2])
    except ValueError:
        degree = -1
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ShapeError("sh", sh.shape, sh_pattern)
    dtype, device = named[0][1].dtype, named[0][1].device
    for name, t in named:
        if not t.is_floating_point():
            raise InputError(f"{name} must be a floating-point tensor, got {t.dtype}")
        if t.dtype != dtype or t.device != device:
            raise InputError(
                f"{name} is {t.dtype} on {t.device}, but means is {dtype} on {device}: "
                "all Gaussian parameters must share one dtype and device"
            )


@dataclass
class GaussianMaps(_Parameters):
    """One Gaussian per pixel of ``B`` views, each view's in its own camera frame.

    The same pre-activation parameterisation as :class:`Gaussians`, laid out as images. The
    Gaussian-prediction stages return one map per view (``B = 1``, since the two views may differ
    in size); the neural Gaussian head returns both views of a batch of pairs in view 0's frame.

    Attributes:
        means: centres in the view's camera frame. [B, H, W, 3]
        log_scales: natural log of the standard deviations along the local axes. [B, H, W, 3]
        quats: (w, x, y, z) rotations in the view's camera frame, not necessarily normalised. [B, H, W, 4]
        opacity_logits: opacities before the sigmoid. [B, H, W]
        sh: SH coefficients, band-major (``sh[..., 0, :]`` is the DC term of R, G, B). [B, H, W, K, 3]
        valid: pixels that carry a Gaussian; None: every pixel. [B, H, W] bool
        cam_to_world: each view's camera-to-world transform; None: the identity (the maps are
            already in the world frame). [B, 4, 4] float64

    Construction checks shapes and dtypes like :class:`Gaussians` (:class:`~macsplat_cli.errors.ShapeError`,
    :class:`~macsplat_cli.errors.InputError`).
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    valid: torch.Tensor | None = None
    cam_to_world: torch.Tensor | None = None

    def __post_init__(self) -> None:
        check_shape(self.means, ("B", "H", "W", 3), "means")
        b, h, w = self.means.shape[:3]
        check_shape(self.log_scales, (b, h, w, 3), "log_scales")
        check_shape(self.quats, (b, h, w, 4), "quats")
        check_shape(self.opacity_logits, (b, h, w), "opacity_logits")
        check_shape(self.sh, (b, h, w, "K", 3), "sh")
        _check_sh_and_dtypes(self._named(), "[B, H, W, K, 3] with K in {1, 4, 9, 16}")
        if self.valid is not None:
            check_shape(self.valid, (b, h, w), "valid")
            if self.valid.dtype != torch.bool or self.valid.device != self.means.device:
                raise InputError(
                    f"valid must be a bool tensor on {self.means.device}, got {self.valid.dtype} on {self.valid.device}"
                )
        if self.cam_to_world is not None:
            check_shape(self.cam_to_world, (b, 4, 4), "cam_to_world")
            if not self.cam_to_world.is_floating_point():
                raise InputError(f"cam_to_world must be a floating-point tensor, got {self.cam_to_world.dtype}")

    # ------------------------------------------------------------------ properties
    @property
    def size(self) -> tuple[int, int]:
        """(H, W)"""
        return int(self.means.shape[1]), int(self.means.shape[2])

    @property
    def batch(self) -> int:
        """B, the number of views."""
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[-2])

    def valid_mask(self) -> torch.Tensor:
        """``valid``, or all True when it is None. [B, H, W] bool"""
        if self.valid is not None:
            return self.valid
        return torch.ones(self.means.shape[:3], dtype=torch.bool, device=self.device)

    def cam_to_world_or_identity(self, dtype: torch.dtype | None = None) -> torch.Tensor:
        """``cam_to_world``, or the identity when it is None (the maps are in the world frame). [B, 4, 4]

        Args:
            dtype: the dtype wanted, on the maps' device; None: ``cam_to_world`` as stored (float64 for the identity).
        """
        if self.cam_to_world is not None:
            return self.cam_to_world if dtype is None else self.cam_to_world.to(device=self.device, dtype=dtype)
        eye = torch.eye(4, dtype=torch.float64 if dtype is None else dtype, device=self.device)
        return eye.expand(self.batch, 4, 4)

    # ------------------------------------------------------------------ conversion
    def to_gaussians(self) -> Gaussians:
        """The valid pixels' Gaussians of all ``B`` views, in the world frame (view 0's pixels first, row-major).

        Each view's means and rotations are moved by its ``cam_to_world`` ``[R | t]``: ``μ = R·μ_cam + t``
        (in the maps' dtype), ``q = q(R) ⊗ q_cam``; scales, opacities and SH are copied unchanged (SH
        coefficients are taken as world-frame quantities). Without ``cam_to_world`` every value is
        copied bit for bit. Differentiable with respect to the five maps.
        """
        parts = []
        k = self.sh.shape[-2]
        for b in range(self.batch):
            flat = [t[b].reshape(-1, *t.shape[3:]) for t in self.tensors()]  # [HW, ·]
            if self.valid is not None:
                sel = self.valid[b].reshape(-1).nonzero().squeeze(1)
                flat = [t[sel] for t in flat]
            means, log_scales, quats, opacity_logits, sh = flat
            if self.cam_to_world is not None:
                T = self.cam_to_world[b].to(device=self.device, dtype=self.dtype)
                means = means @ T[:3, :3].T + T[:3, 3]
                q = rotmat_to_quat_np(T[:3, :3].detach().cpu().double().numpy())
                q_c2w = torch.as_tensor(q, dtype=self.dtype, device=self.device)
                quats = quat_multiply(q_c2w.expand(quats.shape[0], 4), quats)
            parts.append(Gaussians(means, log_scales, quats, opacity_logits, sh.reshape(-1, k, 3)))
        if len(parts) == 1:
            return parts[0]
        if not parts:
            return Gaussians(*(t.reshape(0, *t.shape[3:]) for t in self.tensors()))
        return Gaussians.cat(parts)

    def view(self, k: int) -> GaussianMaps:
        """View ``k`` alone (``B = 1``), sharing this map's storage."""
        if not -self.batch <= k < self.batch:
            raise IndexError(f"view {k} of GaussianMaps with {self.batch} view(s)")
        sl = slice(k % self.batch, k % self.batch + 1)
        return _maps(
            [t[sl] for t in self.tensors()],
            valid=None if self.valid is None else self.valid[sl],
            cam_to_world=None if self.cam_to_world is None else self.cam_to_world[sl],
        )

    @staticmethod
    def cat(parts: Sequence[GaussianMaps]) -> GaussianMaps:
        """Concatenate maps of the same size (H, W) along ``B``; the SH degree becomes the highest one (zero-padded).

        ``valid`` (``cam_to_world``) is None only if it is None in every part; otherwise missing ones
        become all-True (the identity).
        """
        if not parts:
            raise ValueError("cat() needs at least one GaussianMaps")
        size = parts[0].size
        for p in parts:
            if p.size != size:
                raise InputError(f"cannot concatenate GaussianMaps of sizes {size} and {p.size} (H, W)")
        k = max(p.sh.shape[-2] for p in parts)

        def pad(sh: torch.Tensor) -> torch.Tensor:
            return F.pad(sh, (0, 0, 0, k - sh.shape[-2]))

        valid = None
        if any(p.valid is not None for p in parts):
            valid = torch.cat([p.valid_mask() for p in parts])
        c2w = None
        given = [p.cam_to_world for p in parts if p.cam_to_world is not None]
        if given:
            eye = torch.eye(4, dtype=given[0].dtype, device=given[0].device)
            c2w = torch.cat(
                [p.cam_to_world.to(eye) if p.cam_to_world is not None else eye.expand(p.batch, 4, 4) for p in parts]
            )
        return GaussianMaps(
            means=torch.cat([p.means for p in parts]),
            log_scales=torch.cat([p.log_scales for p in parts]),
            quats=torch.cat([p.quats for p in parts]),
            opacity_logits=torch.cat([p.opacity_logits for p in parts]),
            sh=torch.cat([pad(p.sh) for p in parts]),
            valid=valid,
            cam_to_world=c2w,
        )

    # ------------------------------------------------------------------ transforms
    def pooled(self, factor: int) -> GaussianMaps:
        """Merge ``factor × factor`` pixel blocks into one Gaussian each (H, W divisible by it).

        Parameters are averaged over each block's valid pixels (a block without one becomes
        invalid); the standard deviations grow by ``factor``, since each Gaussian now covers
        ``factor²`` pixels, and the quaternions are renormalised. ``factor = 1`` returns ``self``.
        """
        if factor == 1:
            return self
        b, (h, w) = self.batch, self.size
        if factor < 1 or h % factor or w % factor:
            raise ValueError(f"a {w}x{h} map cannot be pooled by {factor}")
        v = self.valid_mask().to(self.dtype)[:, None]  # [B, 1, H, W]
        count = F.avg_pool2d(v, factor)  # [B, 1, H/f, W/f]

        def pool(x: torch.Tensor) -> torch.Tensor:  # [B, H, W, ...] → [B, H/f, W/f, C]
            c = x.reshape(b, h, w, -1).permute(0, 3, 1, 2)
            s = F.avg_pool2d(c * v, factor)
            return (s / count.clamp_min(1e-12)).permute(0, 2, 3, 1)

        k = self.sh.shape[-2]
        quats = pool(self.quats)
        return GaussianMaps(
            means=pool(self.means),
            log_scales=pool(self.log_scales) + math.log(factor),
            quats=quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True).clamp_min(1e-12),
            opacity_logits=pool(self.opacity_logits)[..., 0],
            sh=pool(self.sh).reshape(b, h // factor, w // factor, k, 3),
            valid=None if self.valid is None else count[:, 0] > 0,
            cam_to_world=self.cam_to_world,
        )

    def detach(self) -> GaussianMaps:
        """A copy of the parameters outside the graph (cloned: optimising it leaves these maps alone)."""
        return _maps([t.detach().clone() for t in self.tensors()], self.valid, self.cam_to_world)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> GaussianMaps:
        """On ``device``, the parameters in ``dtype`` (``valid`` stays bool, ``cam_to_world`` keeps its dtype)."""
        return _maps(
            [t.to(device=device, dtype=dtype) for t in self.tensors()],
            valid=None if self.valid is None else self.valid.to(device=device),
            cam_to_world=None if self.cam_to_world is None else self.cam_to_world.to(device=device),
        )

    def check_finite(self) -> None:
        """Raise :class:`~macsplat_cli.errors.NonFiniteError` if any parameter or ``cam_to_world`` is NaN or Inf."""
        for name, t in self._named():
            check_finite(t, name)
        if self.cam_to_world is not None:
            check_finite(self.cam_to_world, "cam_to_world")


def _maps(params: list[torch.Tensor], valid: torch.Tensor | None, cam_to_world: torch.Tensor | None) -> GaussianMaps:
    """:class:`GaussianMaps` of the five parameter tensors ``params`` (in field order, as ``tensors()`` gives)."""
    means, log_scales, quats, opacity_logits, sh = params
    return GaussianMaps(means, log_scales, quats, opacity_logits, sh, valid, cam_to_world)
