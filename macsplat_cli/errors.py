"""Typed errors raised by the library.

The CLI converts every :class:`MacsplatError` into one line on stderr and the exit
code carried by its class (``exit_code``):

* ``2`` — bad input or usage (:class:`InputError` and subclasses);
* ``3`` — the input is well formed but the scene cannot be reconstructed
  (:class:`ReconstructionError` and subclasses).
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = [
    "CameraFileError",
    "ImageReadError",
    "InputError",
    "MacsplatError",
    "NonFiniteError",
    "OutputPathError",
    "PlaneTieError",
    "PlyFormatError",
    "ReconstructionError",
    "SameViewError",
    "ShapeError",
]


class MacsplatError(Exception):
    """Base class of every error macsplat raises on purpose."""

    exit_code: int = 1


class InputError(MacsplatError):
    """Bad input or usage: a missing or malformed file, an invalid argument."""

    exit_code = 2


class ShapeError(InputError, ValueError):
    """A tensor does not have the expected shape."""

    def __init__(self, name: str, actual: Sequence[int], expected: str) -> None:
        self.name = name
        self.actual_shape = tuple(int(s) for s in actual)
        self.expected_shape = expected
        super().__init__(f"{name} has shape {list(self.actual_shape)}, expected {expected}")


class NonFiniteError(InputError, ValueError):
    """A tensor holds NaN or Inf where finite values are required."""


class PlyFormatError(InputError):
    """A PLY file is unreadable or lacks the 3DGS properties."""


class CameraFileError(InputError):
    """A camera file is malformed or describes an invalid camera."""


class ImageReadError(InputError):
    """An image file is missing, unreadable or not an image."""


class OutputPathError(InputError):
    """An output path cannot be written."""


class ReconstructionError(MacsplatError):
    """Well-formed input from which no scene can be reconstructed."""

    exit_code = 3


class SameViewError(ReconstructionError):
    """The two photos show the same view: their matches have not moved (no tier's matches can change that)."""


class DatasetError(InputError):
    """An evaluation data set is malformed: a missing file, inconsistent cameras, an unreadable image."""


class PlaneTieError(ReconstructionError):
    """A plane's two relative poses explain the matches and nothing else tells them apart: another tier's matches
    must settle the same contest (the geometry, not the descriptors, makes it)."""
