"""The scene model: a set of 3D Gaussians in the standard 3DGS parameterisation.

Symbols used across macsplat: ``N`` Gaussians, ``K = (d + 1)²`` SH coefficients
per colour channel for SH degree ``d``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ._checks import check_finite, check_shape
from .errors import InputError, ShapeError
from .sh import MAX_SH_DEGREE, rgb_to_sh0, sh_degree_from_bases

__all__ = ["Gaussians", "quat_multiply", "quat_to_rotmat"]


@dataclass
class Gaussians:
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
        try:
            degree = sh_degree_from_bases(self.sh.shape[1])
        except ValueError:
            degree = -1
        if not 0 <= degree <= MAX_SH_DEGREE:
            raise ShapeError("sh", self.sh.shape, "[N, K, 3] with K in {1, 4, 9, 16}")
        dtype, device = self.means.dtype, self.means.device
        for name, t in self._named():
            if not t.is_floating_point():
                raise InputError(f"{name} must be a floating-point tensor, got {t.dtype}")
            if t.dtype != dtype or t.device != device:
                raise InputError(
                    f"{name} is {t.dtype} on {t.device}, but means is {dtype} on {device}: "
                    "all Gaussian parameters must share one dtype and device"
                )

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
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

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
    def _named(self) -> list[tuple[str, torch.Tensor]]:
        return [
            ("means", self.means),
            ("log_scales", self.log_scales),
            ("quats", self.quats),
            ("opacity_logits", self.opacity_logits),
            ("sh", self.sh),
        ]

    def tensors(self) -> list[torch.Tensor]:
        """The five parameter tensors, in field order (e.g. to hand to an optimiser)."""
        return [t for _, t in self._named()]

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


def quat_to_rotmat(quats: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rotation matrices from (w, x, y, z) quaternions of any non-zero norm. [..., 4] → [..., 3, 3]

    Uses ``R = I + s·(...)`` with ``s = 2 / |q|²``, which equals the usual formula for
    the normalised quaternion. Quaternions with ``|q|² ≤ eps`` give the identity
    with zero gradient instead of the NaN/1e12 gradients of normalising a zero vector.
    """
    w, x, y, z = quats.unbind(-1)
    n2 = (quats * quats).sum(-1)
    ok = n2 > eps
    s = torch.where(ok, 2.0 / torch.where(ok, n2, torch.ones_like(n2)), torch.zeros_like(n2))
    r = torch.stack(
        [
            1 - s * (y * y + z * z),
            s * (x * y - w * z),
            s * (x * z + w * y),
            s * (x * y + w * z),
            1 - s * (x * x + z * z),
            s * (y * z - w * x),
            s * (x * z - w * y),
            s * (y * z + w * x),
            1 - s * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(*quats.shape[:-1], 3, 3)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b`` of (w, x, y, z) quaternions: rotation ``a`` after ``b``. [..., 4]"""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )
