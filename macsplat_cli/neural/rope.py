"""CroCo's 2-D rotary position embedding (RoPE2D), in plain PyTorch.

Each attention head of dimension ``Dh`` is split in two halves: the first ``Dh/2`` channels are
rotated by the token's row (y) index, the last ``Dh/2`` by its column (x) index. Within a half of
size ``D' = Dh/2`` the rotation is the non-interleaved ("rotate-half") form: channel ``j`` is paired
with channel ``j + D'/2`` and the pair is rotated by ``pos · base^(-2i/D')``, ``i = j mod D'/2``.
Rotating q and k this way makes ``q·k`` depend only on the *difference* of the two tokens' grid
positions. There are no parameters and nothing is cached, so any patch grid works.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RoPE2D", "patch_positions"]


def patch_positions(h: int, w: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Integer (y, x) grid positions of ``h × w`` patch tokens in row-major token order. [h·w, 2] int64"""
    ys = torch.arange(h, device=device)
    xs = torch.arange(w, device=device)
    return torch.cartesian_prod(ys, xs).reshape(h * w, 2)


def _rotate_half(x: torch.Tensor) -> torch.Tensor:
    a, b = x.chunk(2, dim=-1)
    return torch.cat((-b, a), dim=-1)


class RoPE2D(nn.Module):
    """Apply 2-D RoPE to per-head queries or keys.

    Args:
        freq: base frequency (CroCo's ``RoPE100`` → 100).
    """

    def __init__(self, freq: float = 100.0) -> None:
        super().__init__()
        self.freq = float(freq)

    def _rotate_1d(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """``x: [B, heads, N, D']``, ``pos: [B or 1, N]`` → ``[B, heads, N, D']``."""
        d = x.shape[-1]
        dtype = torch.float64 if x.dtype == torch.float64 else torch.float32  # angles at ≥ float32 precision
        inv_freq = self.freq ** (-torch.arange(0, d, 2, device=x.device, dtype=dtype) / d)  # [D'/2]
        angles = pos.to(dtype)[..., None] * inv_freq  # [B, N, D'/2]
        angles = torch.cat((angles, angles), dim=-1)[:, None]  # [B, 1, N, D']
        cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
        return x * cos + _rotate_half(x) * sin

    def forward(
        self,
        x: torch.Tensor,  # [B, heads, N, Dh]
        positions: torch.Tensor,  # [B, N, 2] or [N, 2], (y, x) integer grid indices
    ) -> torch.Tensor:
        """Rotate ``x`` by its tokens' grid positions. Returns ``[B, heads, N, Dh]``."""
        dh = x.shape[-1]
        assert dh % 4 == 0, f"RoPE2D needs a head dimension divisible by 4, got {dh}"
        if positions.dim() == 2:
            positions = positions[None]
        assert positions.shape[-2:] == (x.shape[-2], 2), (positions.shape, x.shape)
        y_half, x_half = x.chunk(2, dim=-1)
        return torch.cat(
            (self._rotate_1d(y_half, positions[..., 0]), self._rotate_1d(x_half, positions[..., 1])), dim=-1
        )

    def extra_repr(self) -> str:
        return f"freq={self.freq:g}"
