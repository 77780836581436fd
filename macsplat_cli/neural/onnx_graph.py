"""Producing and editing the ONNX file of a predictor: the exporter call (dynamic sizes, its chatter kept off the
CLI's output), the tidied graph, half precision, the opset probe, the metadata, the int8 quantisation.

The steps :func:`~.onnx_export.export_onnx` runs, in its order and with its all-or-nothing files.
"""

from __future__ import annotations

import contextlib
import copy
import io
import logging
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..errors import InputError
from .onnx_format import INPUT_NAMES, METADATA_KEY, OnnxPredictorInfo
from .predictor import PairPredictor

__all__ = [
    "EXTERNAL_DATA_BYTES",
    "HalfPrecision",
    "check_opset",
    "quantize_int8",
    "quiet_exporter",
    "set_metadata",
    "tidy_graph",
    "trace_program",
]

logger = logging.getLogger(__name__)

EXTERNAL_DATA_BYTES = 1_800_000_000
"""Above this many bytes of weights the model is saved in the external-data format (protobuf's limit is 2 GiB)."""


@contextlib.contextmanager
def quiet_exporter() -> Iterator[None]:
    """The exporter prints its progress to stdout and warns about harmless things: keep both off the CLI's output."""
    buf = io.StringIO()
    with warnings.catch_warnings(), contextlib.redirect_stdout(buf):
        warnings.simplefilter("ignore")
        exporter_logs = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._dynamo", "onnxscript")]
        levels = [lg.level for lg in exporter_logs]
        for lg in exporter_logs:
            lg.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for lg, level in zip(exporter_logs, levels):
                lg.setLevel(level)
            for line in buf.getvalue().splitlines():
                logger.debug("exporter: %s", line)


class HalfPrecision(nn.Module):
    """The predictor in float16 between float32 inputs and outputs (what ``--fp16`` exports)."""

    def __init__(self, predictor: PairPredictor) -> None:
        super().__init__()
        self.inner = copy.deepcopy(predictor).half().eval()

    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(t.float() for t in self.inner(img0.half(), img1.half()))


_OPSET_CACHE: dict[int, str | None] = {}


def check_opset(opset: int) -> None:
    """Export a two-layer probe at ``opset`` and load it in onnxruntime (about a second).

    torch's exporter silently falls back to another opset when it cannot produce the one asked for;
    this catches that before the long export.

    Raises:
        InputError: the installed exporter or onnxruntime cannot produce/run ``opset``.
    """
    if opset not in _OPSET_CACHE:
        from .onnx_runtime import _import_ort

        ort = _import_ort()  # and onnxruntime's own log silenced

        probe = nn.Sequential(nn.Linear(4, 8), nn.GELU(), nn.LayerNorm(8))
        problem: str | None = None
        try:
            with quiet_exporter():
                prog = torch.onnx.export(probe, (torch.randn(2, 4),), dynamo=True, opset_version=opset)
            assert prog is not None  # dynamo=True returns the program (a failure raises, caught below)
            got = {i.domain or "ai.onnx": i.version for i in prog.model_proto.opset_import}.get("ai.onnx")
            if got != opset:
                problem = f"it produced opset {got}"
            else:
                ort.InferenceSession(prog.model_proto.SerializeToString(), providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - exporter and runtime raise many types
            problem = f"{type(e).__name__}: {' '.join(str(e).split())[:200]}"
        _OPSET_CACHE[opset] = problem
    problem = _OPSET_CACHE[opset]
    if problem is not None:
        import onnxruntime

        raise InputError(
            f"--opset {opset}: the installed exporter (torch {torch.__version__}) and onnxruntime "
            f"{onnxruntime.__version__} cannot produce and run it ({problem}); 18 and 20 (the default) are the safe "
            "choices"
        )


def trace_program(
    module: nn.Module, example: tuple[torch.Tensor, ...], opset: int, names: tuple[str, ...], dynamic: bool
) -> Any:
    """``torch.onnx.export`` of ``module`` at ``example`` (an ``ONNXProgram``), inputs and outputs named; with
    ``dynamic``, batch, H and W symbolic (H and W multiples of 16), its output quieted."""
    dynamic_shapes = None
    if dynamic:
        from torch.export import Dim

        batch = Dim("batch", min=1, max=64)
        ph, pw = Dim("ph", min=2, max=512), Dim("pw", min=2, max=512)
        spec = {0: batch, 2: 16 * ph, 3: 16 * pw}
        dynamic_shapes = {"img0": spec, "img1": spec}
    with quiet_exporter(), torch.no_grad():
        return torch.onnx.export(
            module, example, dynamo=True, opset_version=opset, input_names=list(INPUT_NAMES),
            output_names=list(names), dynamic_shapes=dynamic_shapes, optimize=True, verbose=False,
        )  # fmt: skip


def tidy_graph(model: Any, dynamic: bool) -> None:
    """Readable symbolic sizes (``batch, 2, H, W, …``) instead of the exporter's expressions; no per-node
    tracing metadata (stack traces with local paths, ~1 KB a node)."""
    import onnx_ir as ir

    for node in model.graph.all_nodes() if hasattr(model.graph, "all_nodes") else model.graph:
        node.metadata_props.clear()

    for inp in model.graph.inputs:
        if dynamic:
            inp.shape = ir.Shape(["batch", 3, "H", "W"])
    for out in model.graph.outputs:
        if out.shape is None:
            continue
        dims = list(out.shape)
        if dynamic:
            dims[0], dims[2], dims[3] = "batch", "H", "W"
        out.shape = ir.Shape(dims)


def set_metadata(path: Path, info: OnnxPredictorInfo) -> None:
    """Rewrite the graph file's metadata (external weights are left where they are)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    props = {p.key: p.value for p in model.metadata_props}
    props[METADATA_KEY] = info.to_json()
    del model.metadata_props[:]
    for k, v in props.items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(path))


def quantize_int8(src: Path, dst: Path) -> None:
    from onnxruntime.quantization import QuantType, quantize_dynamic

    external = src.with_name(src.name + ".data").exists() and os.path.getsize(src.with_name(src.name + ".data")) > 4 * (
        EXTERNAL_DATA_BYTES
    )  # int8 weights are 4× smaller: external data only when they would still pass the limit
    with quiet_exporter():
        logging.disable(logging.WARNING)  # ORT's quantiser warns on the root logger ("consider pre-processing")
        try:
            quantize_dynamic(
                str(src), str(dst), weight_type=QuantType.QInt8, per_channel=True, use_external_data_format=external
            )
        finally:
            logging.disable(logging.NOTSET)
