"""The ONNX predictor file: its input/output contract, its metadata, and the parity check.

A macsplat ONNX predictor (``macsplat export-onnx``) is :class:`~.predictor.PairPredictor`'s
``forward`` as a graph:

* inputs ``img0``, ``img1``: float32 RGB in [0, 1], ``[B, 3, H, W]``, both the same size, ``H`` and ``W``
  multiples of 16 (dynamic), or exactly the size in the metadata (a fixed-size export);
* outputs, in order: ``pts3d [B, 2, H, W, 3]``, ``conf [B, 2, H, W]``, ``desc [B, 2, H, W, D]``,
  ``desc_conf [B, 2, H, W]`` and, with a Gaussian head, ``gaussians_means``, ``gaussians_log_scales``,
  ``gaussians_quats`` (wxyz), ``gaussians_opacity_logits``, ``gaussians_sh [B, 2, H, W, K, 3]`` —
  every output float32, views stacked on dim 1, in view 0's camera frame.

The model's ``metadata_props`` carry :class:`OnnxPredictorInfo` (one JSON string under
``macsplat.predictor``): the format version, the input size rule and normalisation, each output's
meaning, the macsplat version, the precision, the sha256 of the checkpoints it came from, and the
parity figures of the export.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..errors import InputError, MacsplatError

__all__ = [
    "FORMAT",
    "INPUT_NAMES",
    "METADATA_KEY",
    "OUTPUT_MEANINGS",
    "PARITY_TOLERANCE",
    "OnnxPredictorError",
    "OnnxPredictorInfo",
    "ParityError",
    "ParityReport",
    "compare_outputs",
    "expected_output_names",
    "sample_pair",
]

FORMAT = "macsplat-pair-predictor"
FORMAT_VERSION = 1
METADATA_KEY = "macsplat.predictor"
INPUT_NAMES = ("img0", "img1")
PATCH = 16

OUTPUT_MEANINGS: dict[str, str] = {
    "pts3d": "[B, 2, H, W, 3] float32: both views' point maps in view 0's camera frame",
    "conf": "[B, 2, H, W] float32: point-map confidence (>= 1)",
    "desc": "[B, 2, H, W, D] float32: matching descriptors (fused with DINOv3 features when the fusion ran)",
    "desc_conf": "[B, 2, H, W] float32: descriptor confidence, the activation's floor removed (>= 0)",
    "gaussians_means": "[B, 2, H, W, 3] float32: Gaussian centres, view 0's camera frame",
    "gaussians_log_scales": "[B, 2, H, W, 3] float32: log standard deviations",
    "gaussians_quats": "[B, 2, H, W, 4] float32: rotations, (w, x, y, z), not normalised",
    "gaussians_opacity_logits": "[B, 2, H, W] float32: opacity before the sigmoid",
    "gaussians_sh": "[B, 2, H, W, K, 3] float32: spherical-harmonic colour, band-major",
}
INPUT_RULE = "img0, img1: float32 RGB in [0, 1], [B, 3, H, W], same size; H and W multiples of 16"
NORMALISATION = "none outside the graph: RGB in [0, 1]; the graph maps it to the backbone's [-1, 1]"

PARITY_TOLERANCE: dict[str, float] = {"fp32": 1e-3, "fp16": 3e-2, "int8": 0.25}
"""Largest accepted error of an exported output against the fp32 torch predictor, relative to the
output's range (``max|onnx − torch| / max|torch|``), by the precision of the file. fp32 differs by
summation order only; fp16 by its 11-bit mantissa; int8 (dynamic quantisation of the weights and
activations of every matrix product) changes the network itself, so its bound only catches a broken
graph — its figures are printed for the user to judge."""


class OnnxPredictorError(InputError):
    """An ONNX file that is not a macsplat predictor (or one this version cannot run)."""


class ParityError(MacsplatError):
    """onnxruntime's outputs disagree with torch's beyond the tolerance: the export is not kept."""

    exit_code = 3

    def __init__(self, message: str, report: ParityReport | None = None) -> None:
        super().__init__(message)
        self.report = report


def expected_output_names(gaussian_head: bool) -> tuple[str, ...]:
    """The outputs of a predictor with or without a Gaussian head, in order."""
    names = tuple(OUTPUT_MEANINGS)
    return names if gaussian_head else names[:4]


@dataclass
class OnnxPredictorInfo:
    """What an ONNX predictor says about itself (its ``macsplat.predictor`` metadata).

    Attributes:
        precision: ``"fp32"``, ``"fp16"`` (computed in half precision, float32 in and out) or ``"int8"``.
        dynamic: any ``H``, ``W`` multiple of 16; False: exactly ``size``.
        size: the export's sample size ``(W, H)`` (the only size when not dynamic).
        network: the network's description; fusion: the fusion's (or why it is skipped).
        fusion_enabled: the descriptors are fused with DINOv3 features.
        dino: ``{"name", "patch_size", "embed_dim"}`` of the DINOv3 encoder, or None.
        desc_dim: descriptor width ``D``; gaussian_head: the Gaussian outputs are present.
        outputs: output names in order → meaning.
        sources: the checkpoints it was exported from: role → ``{"path", "sha256"}``.
        config: the predictor's configuration (:func:`~.predictor_io.predictor_config`).
        parity: the export's parity check (:meth:`ParityReport.to_dict`).
    """

    precision: str
    dynamic: bool
    size: tuple[int, int]
    network: str
    fusion: str
    fusion_enabled: bool
    desc_dim: int
    gaussian_head: bool
    dino: dict[str, Any] | None = None
    opset: int | None = None
    outputs: dict[str, str] = field(default_factory=dict)
    sources: dict[str, dict[str, str]] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    parity: dict[str, Any] | None = None
    macsplat_version: str = ""
    format: str = FORMAT
    format_version: int = FORMAT_VERSION
    input: str = INPUT_RULE
    normalisation: str = NORMALISATION

    def to_json(self) -> str:
        from .._json import to_jsonable

        return json.dumps(to_jsonable(self), allow_nan=False, sort_keys=False)

    @classmethod
    def from_json(cls, text: str, source: str) -> OnnxPredictorInfo:
        """Parse the metadata string.

        Raises:
            OnnxPredictorError: not JSON, another format, a newer format version, or missing fields.
        """
        try:
            doc = json.loads(text)
        except (ValueError, RecursionError) as e:
            raise OnnxPredictorError(f"{source}: its macsplat metadata is not JSON ({e})") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise OnnxPredictorError(f"{source}: its metadata is not a {FORMAT}'s")
        if not isinstance(doc.get("format_version"), int) or doc["format_version"] > FORMAT_VERSION:
            raise OnnxPredictorError(
                f"{source}: format version {doc.get('format_version')!r}; this macsplat reads version "
                f"{FORMAT_VERSION} (re-export it, or update macsplat)"
            )
        names = {f.name for f in dataclasses.fields(cls)}
        try:
            info = cls(**{k: v for k, v in doc.items() if k in names})
            info.size = (int(info.size[0]), int(info.size[1]))
        except (TypeError, ValueError, IndexError) as e:
            raise OnnxPredictorError(f"{source}: incomplete macsplat metadata ({e})") from None
        if info.precision not in PARITY_TOLERANCE:
            raise OnnxPredictorError(f"{source}: unknown precision {info.precision!r} in its metadata")
        return info

    def fusion_detail(self, size: tuple[int, int]) -> str:
        """One line for the report: what the fusion does on an ``(H, W)`` input."""
        if not self.fusion_enabled or self.dino is None:
            return "semantic fusion skipped: not in the exported predictor; descriptors unchanged"
        p = int(self.dino["patch_size"])
        return (
            f"semantic fusion applied: DINOv3 {self.dino['name']} features {size[0] // p}×{size[1] // p}×"
            f"{self.dino['embed_dim']} → descriptors {size[0]}×{size[1]}×{self.desc_dim}"
        )


# ============================================================================================= parity
def sample_pair(size: tuple[int, int], seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A deterministic, photo-like pair at ``size = (W, H)``: a ray-traced room seen from two cameras
    15° apart (texture, edges, depth), so that the network sees what it was trained on. ``[1, 3, H, W]`` each."""
    from ..datasets import synthetic as syn

    w, h = size
    scene = syn.make_scene("room", seed)
    cams = syn.orbit_pair("room", 15, width=w, height=h, fov_deg=60.0)
    imgs = [torch.from_numpy(np.ascontiguousarray(syn.render(scene, c).image, np.float32)) for c in cams]
    return tuple(im.permute(2, 0, 1)[None].clamp(0, 1).contiguous() for im in imgs)  # type: ignore[return-value]


@dataclass
class ParityReport:
    """onnxruntime against the fp32 torch predictor on one sample pair, per output.

    Attributes:
        rows: one ``{"output", "max_abs", "max_rel", "ok"}`` per output (``max_rel``: ``max_abs`` over the
            largest magnitude of the torch output).
        tolerance: the bound on ``max_rel``; precision: the file's; size: the sample's ``(W, H)``.
    """

    rows: list[dict[str, Any]]
    tolerance: float
    precision: str
    size: tuple[int, int]
    provider: str = "CPUExecutionProvider"

    @property
    def ok(self) -> bool:
        return all(r["ok"] for r in self.rows)

    @property
    def worst(self) -> dict[str, Any]:
        return max(self.rows, key=lambda r: r["max_rel"])

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "precision": self.precision,
            "tolerance": self.tolerance,
            "sample_size": list(self.size),
            "provider": self.provider,
            "reference": "torch fp32, the same weights",
            "outputs": self.rows,
        }


def compare_outputs(
    names: tuple[str, ...] | list[str],
    onnx_outputs: list[np.ndarray],
    torch_outputs: tuple[torch.Tensor, ...],
    tolerance: float,
) -> list[dict[str, Any]]:
    """Per-output max abs and range-relative errors (non-finite values count as an infinite error)."""
    rows = []
    for name, got, ref in zip(names, onnx_outputs, torch_outputs):
        r = ref.detach().double().cpu().numpy()
        g = np.asarray(got, dtype=np.float64)
        if g.shape != r.shape:
            rows.append({"output": name, "max_abs": math.inf, "max_rel": math.inf, "ok": False,
                         "detail": f"shape {list(g.shape)} vs torch {list(r.shape)}"})  # fmt: skip
            continue
        finite = bool(np.isfinite(g).all() == np.isfinite(r).all() and np.isfinite(g).all())
        err = float(np.max(np.abs(g - r))) if finite and g.size else (0.0 if finite else math.inf)
        scale = float(np.max(np.abs(r))) if r.size else 0.0
        rel = err / max(scale, 1e-12) if math.isfinite(err) else math.inf
        rows.append({"output": name, "max_abs": err, "max_rel": rel, "ok": bool(rel <= tolerance)})
    return rows
