"""Boundary checks that raise typed errors (internal helpers use plain asserts)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from .errors import NonFiniteError, ShapeError


def check_shape(x: torch.Tensor, expected: Sequence[int | str], name: str) -> None:
    """Check ``x.shape`` against a pattern such as ``("N", 3)``.

    Strings are named dimensions: the same name must have the same size
    everywhere in the pattern. ``"*"`` matches any size.
    """
    sizes: dict[str, int] = {}
    ok = x.dim() == len(expected)
    if ok:
        for dim, want in zip(x.shape, expected):
            if not isinstance(want, str):  # an int, or a symbolic size while tracing for export
                ok = dim == want
            elif want != "*":
                ok = sizes.setdefault(want, dim) == dim
            if not ok:
                break
    if not ok:
        raise ShapeError(name, x.shape, "[" + ", ".join(str(e) for e in expected) + "]")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise :class:`NonFiniteError` if ``x`` holds a NaN or an Inf."""
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise NonFiniteError(f"{name} holds {bad} non-finite value(s) (NaN or Inf)")
