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
from typing import Any, TypeGuard

import numpy as np
import torch

from ..errors import InputError, MacsplatError

__all__ = [
    "ALLOWED_OPS",
    "FORMAT",
    "INPUT_NAMES",
    "MAX_METADATA_BYTES",
    "MAX_SIDE",
    "METADATA_KEY",
    "OUTPUT_MEANINGS",
    "PARITY_TOLERANCE",
    "OnnxPredictorError",
    "OnnxPredictorInfo",
    "ParityError",
    "ParityReport",
    "check_graph",
    "compare_outputs",
    "expected_output_names",
]

FORMAT = "macsplat-pair-predictor"
FORMAT_VERSION = 1
METADATA_KEY = "macsplat.predictor"
INPUT_NAMES = ("img0", "img1")
PATCH = 16
MAX_SIDE = 8192
"""Largest image side a predictor file may declare (its ``size``): the exporter's dynamic height and width
go up to 512 patches of 16 px."""
MAX_DESC_DIM = 4096
"""Widest descriptor a predictor file may declare (MASt3R's are 24-d)."""
MAX_METADATA_BYTES = 1024 * 1024
"""Largest ``macsplat.predictor`` metadata string read (an export writes a few KB)."""
MAX_TEXT_FIELD = 10_000
"""Longest text field of the metadata (names and descriptions: a few hundred characters)."""

ALLOWED_OPS: frozenset[tuple[str, str]] = frozenset(
    ("", op)
    for op in (
        # what torch 2.13's exporter writes for the predictor (fp32, --fp16, --fixed-size) at opsets 18 and 20
        "Add", "Cast", "Clip", "Concat", "Conv", "ConvTranspose", "Cos", "DepthToSpace", "Div", "Erf", "Exp",
        "Expand", "Gather", "Gelu", "Greater", "LayerNormalization", "MatMul", "Min", "Mul", "Neg", "Range",
        "ReduceL2", "Relu", "Reshape", "Resize", "Shape", "Sin", "Slice", "Softmax", "Split", "Squeeze", "Sub",
        "Tile", "Transpose", "Unsqueeze", "Where",
        # onnxruntime's dynamic int8 quantiser (--quantize int8)
        "ConvInteger", "DequantizeLinear", "DynamicQuantizeLinear", "MatMulInteger",
    )
)  # fmt: skip
"""``(domain, op type)`` of every node ``export-onnx`` writes ("" is the standard ``ai.onnx`` domain): a file
with any other node (control flow such as ``Loop``/``If``/``Scan``, which can run without end; a custom
domain) was not made by the exporter and is refused before onnxruntime loads it. ``tests/neural/test_onnx.py``
checks every export against it, and the exporter refuses to write a file outside it."""

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


def check_graph(model: Any, source: str) -> None:
    """Refuse a graph ``export-onnx`` cannot have written, before onnxruntime loads it.

    Every node must be in :data:`ALLOWED_OPS`; no node may carry a subgraph (a ``GRAPH``/``GRAPHS``
    attribute); the model may define no functions of its own; every output must be a float tensor.

    Args:
        model: the ``onnx.ModelProto`` (its weights need not be loaded).
        source: the file, for messages.

    Raises:
        OnnxPredictorError: the first offending node, function or output, named.
    """
    import onnx

    if len(model.functions):
        names = sorted({f"{f.domain}:{f.name}" if f.domain else f.name for f in model.functions})
        raise OnnxPredictorError(
            f"{source} defines its own ONNX functions ({', '.join(names[:5])}): not a file export-onnx writes"
        )
    subgraph_types = (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
    unknown: dict[str, int] = {}
    for node in model.graph.node:
        domain = "" if node.domain in ("", "ai.onnx") else node.domain
        if (domain, node.op_type) not in ALLOWED_OPS:
            key = f"{domain}:{node.op_type}" if domain else node.op_type
            unknown[key] = unknown.get(key, 0) + 1
            continue
        for attr in node.attribute:
            if attr.type in subgraph_types or attr.HasField("g") or len(attr.graphs):
                raise OnnxPredictorError(
                    f"{source}: node {node.name or node.op_type!r} ({node.op_type}) carries a subgraph in its "
                    f"attribute {attr.name!r}: not a file export-onnx writes"
                )
    if unknown:
        listed = ", ".join(f"{k} ×{n}" if n > 1 else k for k, n in sorted(unknown.items())[:8])
        raise OnnxPredictorError(
            f"{source} uses operators export-onnx never writes ({listed}): refused (control flow and custom "
            "operators are not run)"
        )
    for out in model.graph.output:
        kind = out.type.WhichOneof("value")
        if kind != "tensor_type" or out.type.tensor_type.elem_type != onnx.TensorProto.FLOAT:
            what = (
                onnx.TensorProto.DataType.Name(out.type.tensor_type.elem_type).lower()
                if kind == "tensor_type" else (kind or "untyped")
            )  # fmt: skip
            raise OnnxPredictorError(f"{source}: output {out.name} is {what}, expected a float tensor")


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
            OnnxPredictorError: not JSON (or over :data:`MAX_METADATA_BYTES`), another format, a newer format
                version, missing fields, or a field of the wrong type or range (the message names it).
        """
        from .._limits import MAX_JSON_DEPTH, json_depth

        if len(text) > MAX_METADATA_BYTES:
            raise OnnxPredictorError(
                f"{source}: its macsplat metadata is {len(text):,} characters (at most {MAX_METADATA_BYTES:,})"
            )
        try:
            doc = json.loads(text)
        except (ValueError, RecursionError, MemoryError) as e:
            raise OnnxPredictorError(f"{source}: its macsplat metadata is not JSON ({e})") from None
        if json_depth(doc) > MAX_JSON_DEPTH:
            raise OnnxPredictorError(f"{source}: its macsplat metadata is nested too deeply (at most {MAX_JSON_DEPTH})")
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise OnnxPredictorError(f"{source}: its metadata is not a {FORMAT}'s")
        version = doc.get("format_version")
        if not _is_int(version) or not 1 <= version <= FORMAT_VERSION:
            raise OnnxPredictorError(
                f"{source}: format version {version!r}; this macsplat reads version "
                f"{FORMAT_VERSION} (re-export it, or update macsplat)"
            )
        names = {f.name for f in dataclasses.fields(cls)}
        required = [f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING
                    and f.default_factory is dataclasses.MISSING]  # fmt: skip
        missing = [k for k in required if k not in doc]
        if missing:
            raise OnnxPredictorError(f"{source}: incomplete macsplat metadata (missing {', '.join(missing)})")
        _check_metadata(doc, source)
        info = cls(**{k: v for k, v in doc.items() if k in names})
        info.size = (int(info.size[0]), int(info.size[1]))
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


# ============================================================================================= metadata checks
def _is_int(v: Any) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_metadata(doc: dict[str, Any], source: str) -> None:
    """The type and range of every metadata field macsplat reads (what a hostile file could set).

    Raises:
        OnnxPredictorError: the first bad field, named, with what it should be.
    """

    def bad(name: str, expected: str) -> OnnxPredictorError:
        got = json.dumps(doc[name]) if name in doc else "missing"
        got = got if len(got) <= 60 else got[:57] + "..."
        return OnnxPredictorError(f"{source}: its macsplat metadata field {name!r} is {got}: expected {expected}")

    def text(value: Any) -> bool:
        return isinstance(value, str) and len(value) <= MAX_TEXT_FIELD

    def int_in(value: Any, lo: int, hi: int) -> bool:
        return _is_int(value) and lo <= value <= hi

    if doc["precision"] not in PARITY_TOLERANCE:
        raise bad("precision", " or ".join(repr(p) for p in PARITY_TOLERANCE))
    for name in ("dynamic", "fusion_enabled", "gaussian_head"):
        if not isinstance(doc[name], bool):
            raise bad(name, "true or false")
    size = doc["size"]
    if not (isinstance(size, list) and len(size) == 2 and all(int_in(v, 2 * PATCH, MAX_SIDE) and v % PATCH == 0
                                                             for v in size)):  # fmt: skip
        raise bad("size", f"[width, height], multiples of {PATCH} from {2 * PATCH} to {MAX_SIDE}")
    if not int_in(doc["desc_dim"], 1, MAX_DESC_DIM):
        raise bad("desc_dim", f"an integer from 1 to {MAX_DESC_DIM}")
    for name in ("network", "fusion", "macsplat_version", "input", "normalisation"):
        if name in doc and not text(doc[name]):
            raise bad(name, f"text of at most {MAX_TEXT_FIELD:,} characters")
    dino = doc.get("dino")
    if dino is not None and not (
        isinstance(dino, dict) and text(dino.get("name")) and int_in(dino.get("patch_size"), 1, 1024)
        and int_in(dino.get("embed_dim"), 1, 1 << 16)
    ):  # fmt: skip
        raise bad("dino", 'null or {"name": text, "patch_size": 1-1024, "embed_dim": 1-65536}')
    if doc.get("opset") is not None and not int_in(doc["opset"], 1, 1000):
        raise bad("opset", "null or an integer")
    outputs = doc.get("outputs", {})
    if not (isinstance(outputs, dict) and all(text(v) for v in outputs.values())):
        raise bad("outputs", "an object of output name -> text")
    sources = doc.get("sources", {})
    if not (isinstance(sources, dict) and all(isinstance(v, dict) and all(text(b) for b in v.values())
                                              for v in sources.values())):  # fmt: skip
        raise bad("sources", 'an object of role -> {"path": text, "sha256": text}')
    config = doc.get("config", {})
    if not isinstance(config, dict):
        raise bad("config", "an object (the predictor's configuration)")
    backbone = config.get("backbone")
    if backbone is not None:
        img_size = backbone.get("img_size") if isinstance(backbone, dict) else None
        if not isinstance(backbone, dict) or (img_size is not None and not (
            isinstance(img_size, list) and len(img_size) == 2 and all(int_in(v, 1, MAX_SIDE) for v in img_size)
        )):  # fmt: skip
            raise OnnxPredictorError(
                f"{source}: its macsplat metadata field 'config.backbone' is not an object with an img_size of two "
                f"integers from 1 to {MAX_SIDE}"
            )
    if doc.get("parity") is not None and not isinstance(doc["parity"], dict):
        raise bad("parity", "null or an object")


# ============================================================================================= parity
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
