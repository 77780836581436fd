"""LPIPS (the learned perceptual distance of Zhang et al. 2018, VGG variant) from user-supplied weights.

Neither the VGG16 weights nor the LPIPS linear layers can be bundled or downloaded here, and
the ``lpips``/``torchvision`` packages cannot be installed next to the CPU build of torch. This
module is an own implementation of the published metric that reads the two usual files:

* ``vgg16-397923af.pth`` — torchvision's ImageNet VGG16 (keys ``features.{0,2,5,...,28}.weight/bias``;
  the classifier keys are ignored);
* ``vgg.pth`` — the LPIPS v0.1 linear calibration (keys ``lin{0..4}.model.1.weight``, shapes
  ``[1, C, 1, 1]`` for C = 64, 128, 256, 512, 512).

``--lpips-weights`` takes a folder holding both (any ``vgg16*.pth`` plus ``vgg.pth``) or one
``.pth`` file that contains both key sets.

The distance: images in [0, 1] → [-1, 1] → the LPIPS input scaling → VGG16 features after
relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 → each unit-normalised over channels → squared
difference → the linear layer (a 1×1 convolution to one channel) → spatial mean → sum over
the five layers.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import nn

from ._state_dict import StateDictError, check_state_dict_keys, log_sha256
from .errors import InputError

__all__ = ["LPIPS", "LPIPSWeightsError", "load_lpips"]

logger = logging.getLogger(__name__)

# VGG16 "D": convolution widths, "M" = 2×2 max-pool. torchvision indexes conv, ReLU and pool
# modules in one Sequential; the conv layers sit at these indices.
_VGG16: list[int | str] = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_CONV_INDICES = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
_TAPS = (3, 8, 15, 22, 29)  # the ReLU outputs LPIPS compares (relu1_2 ... relu5_3)
_TAP_CHANNELS = (64, 128, 256, 512, 512)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


class LPIPSWeightsError(StateDictError):
    """A missing, unreadable or mismatched LPIPS/VGG weight file (``key``/``file_shape``/``model_shape`` when known)."""


class LPIPS(nn.Module):
    """LPIPS-VGG distance between images in [0, 1]; frozen and always in eval mode."""

    shift: torch.Tensor  # buffers: the input normalisation. [1, 3, 1, 1]
    scale: torch.Tensor

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 3
        for v in _VGG16:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c_in, int(v), 3, padding=1), nn.ReLU()]
                c_in = int(v)
        self.features = nn.Sequential(*layers)  # indices 0..29 as torchvision's (its final pool unused)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in _TAP_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).reshape(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).reshape(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> LPIPS:  # noqa: ARG002 - always frozen
        return super().train(False)

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAPS:
                out.append(x)
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Distance per image.

        Args:
            pred: images in [0, 1]. [B, 3, H, W] or [H, W, 3]
            target: same shape as ``pred``.

        Returns:
            LPIPS distance (lower is more similar). [B] (or a scalar for [H, W, 3] input)
        """
        if pred.shape != target.shape:
            raise InputError(f"LPIPS: image shapes differ: {tuple(pred.shape)} and {tuple(target.shape)}")
        single = pred.dim() == 3
        if single:
            pred, target = pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
        dtype = self.shift.dtype
        x = torch.cat([pred, target]).to(dtype) * 2 - 1
        x = (x - self.shift) / self.scale
        per_tap = []
        for feat, lin in zip(self._taps(x), self.lins):
            f = feat / (feat.square().sum(1, keepdim=True).sqrt() + 1e-10)
            a, b = f.chunk(2)
            per_tap.append(lin((a - b).square()).mean(dim=(1, 2, 3)))
        total = per_tap[0]
        for d in per_tap[1:]:  # summed in tap order
            total = total + d
        return total[0] if single else total

    def spatial(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The distance per pixel (LPIPS's ``spatial=True``): each tap's map upsampled bilinearly (half-pixel
        centres) to the image size, summed over the taps; its mean is :meth:`forward`'s distance when the image
        sides are multiples of 16. ``pred``, ``target``: [H, W, 3] in [0, 1] → [H, W]"""
        if pred.shape != target.shape or pred.dim() != 3:
            raise InputError(f"LPIPS: give two [H, W, 3] images, got {tuple(pred.shape)} and {tuple(target.shape)}")
        h, w = pred.shape[:2]
        dtype = self.shift.dtype
        x = torch.cat([pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]]).to(dtype) * 2 - 1
        x = (x - self.shift) / self.scale
        total = torch.zeros(1, 1, h, w, dtype=dtype, device=x.device)
        for feat, lin in zip(self._taps(x), self.lins):
            f = feat / (feat.square().sum(1, keepdim=True).sqrt() + 1e-10)
            a, b = f.chunk(2)
            total = total + nn.functional.interpolate(lin((a - b).square()), size=(h, w), mode="bilinear",
                                                      align_corners=False)  # fmt: skip
        return total[0, 0]


def _read(path: Path) -> dict[str, torch.Tensor]:
    log_sha256(path, logger, "LPIPS weights")
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch.load raises many kinds on a bad file
        raise LPIPSWeightsError(f"{path}: not a readable PyTorch weight file ({type(e).__name__}: {e})") from e
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise LPIPSWeightsError(f"{path}: expected a state dict, found {type(sd).__name__}")
    return sd


def load_lpips(path: str | Path) -> LPIPS:
    """An :class:`LPIPS` with weights from a folder (``vgg16*.pth`` + ``vgg.pth``) or one file.

    Raises:
        LPIPSWeightsError: missing files, or a key missing or of the wrong shape (the first
            such key is named with both shapes; :func:`._state_dict.check_state_dict_keys`).
    """
    path = Path(path)
    if path.is_dir():
        vgg = sorted(path.glob("vgg16*.pth"))
        lin = path / "vgg.pth"
        if not vgg or not lin.is_file():
            raise LPIPSWeightsError(
                f"{path}: needs torchvision's VGG16 weights (vgg16-397923af.pth) and the LPIPS v0.1 linear "
                "layers (vgg.pth, from the lpips package's weights/v0.1/ folder)"
            )
        sd = {**_read(vgg[0]), **_read(lin)}
    elif path.is_file():
        sd = _read(path)
    else:
        raise LPIPSWeightsError(f"{path}: no such file or folder (LPIPS needs local VGG16 + LPIPS weights)")
    model = LPIPS()
    wanted: dict[str, torch.Tensor] = {}
    for idx in _CONV_INDICES:
        conv = model.features[idx]
        assert isinstance(conv, nn.Conv2d) and conv.bias is not None  # _CONV_INDICES: _VGG16's convolutions
        wanted[f"features.{idx}.weight"] = conv.weight
        wanted[f"features.{idx}.bias"] = conv.bias
    for k, tap in enumerate(model.lins):
        assert isinstance(tap, nn.Conv2d)
        wanted[f"lin{k}.model.1.weight"] = tap.weight
    # The files hold more than LPIPS uses (VGG16's classifier), so unknown keys are ignored.
    expected = {key: param.shape for key, param in wanted.items()}
    check_state_dict_keys(expected, sd, LPIPSWeightsError, source=str(path), model="LPIPS-VGG", allow_unexpected=True)
    with torch.no_grad():
        for key, param in wanted.items():
            param.copy_(sd[key].to(param.dtype))
    logger.debug("LPIPS weights loaded from %s", path)
    return model
