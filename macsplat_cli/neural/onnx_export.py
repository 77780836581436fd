"""Export a :class:`~.predictor.PairPredictor` to ONNX, check it against torch, and keep it only if it agrees.

:func:`export_onnx` traces ``PairPredictor.forward`` with torch's ``torch.export``-based exporter
(RoPE, attention and the DPT heads lower to standard ONNX ops), with the batch and the image height
and width dynamic (``16·k``) — falling back to the sample's fixed size when the exporter cannot keep
them symbolic — writes :class:`~.onnx_format.OnnxPredictorInfo` into the model's metadata, runs
``onnx.checker``, optionally quantises it (onnxruntime's dynamic int8 quantisation), and runs the
**parity check**: onnxruntime and the fp32 torch predictor on a sample pair, each output's error
printed and written beside the file (``<stem>.parity.json``). An output beyond the tolerance fails
the export (:class:`~.onnx_format.ParityError`, exit 3); so does a node the runtime would refuse
(:func:`~.onnx_format.check_graph`; :class:`ExportError`).

Everything is written into a temporary folder beside the output and moved into place at the end:
a failure, or an interrupt, leaves no partial file; a write that fails (a full disk, a folder that refuses
files although ``os.access`` allowed them) is an :class:`~macsplat_cli.errors.OutputPathError` (exit 2).
Models over 2 GB (ViT-L MASt3R in fp32) keep their weights in ``<name>.onnx.data`` beside the graph
(ONNX's external-data format).
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import logging
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from .. import __version__
from .._atomic import check_writable
from .._state_dict import sha256_file
from ..errors import InputError, MacsplatError, OutputPathError
from .onnx_format import (
    INPUT_NAMES,
    MAX_SIDE,
    METADATA_KEY,
    OUTPUT_MEANINGS,
    PARITY_TOLERANCE,
    OnnxPredictorError,
    OnnxPredictorInfo,
    ParityError,
    ParityReport,
    check_graph,
    compare_outputs,
    sample_pair,
)
from .predictor import PairPredictor

__all__ = ["ExportConfig", "ExportError", "ExportResult", "check_opset", "export_onnx", "source_digests"]

logger = logging.getLogger(__name__)

EXTERNAL_DATA_BYTES = 1_800_000_000
"""Above this many bytes of weights the model is saved in the external-data format (protobuf's limit is 2 GiB)."""
QUANTIZE = ("int8",)


class ExportError(MacsplatError):
    """The exporter or onnx.checker failed on the predictor (a bug, or an unsupported configuration)."""


@dataclass
class ExportConfig:
    """Settings of :func:`export_onnx`.

    Args:
        size: the sample pair's ``(W, H)`` (multiples of 16): traced at, parity-checked at, and the only
            size of a fixed-size export.
        opset: the ONNX opset (the default is torch 2.13's exporter's).
        fp16: compute in half precision (float32 inputs and outputs; for GPUs).
        quantize: ``"int8"``: onnxruntime's dynamic quantisation of every matrix product (for CPUs).
        dynamic: dynamic batch, height and width; False: the fixed ``size`` (and batch 1).
        tolerance: parity bound (range-relative); None: :data:`~.onnx_format.PARITY_TOLERANCE` of the precision.
    """

    size: tuple[int, int] = (512, 384)
    opset: int = 20
    fp16: bool = False
    quantize: str | None = None
    dynamic: bool = True
    tolerance: float | None = None

    @property
    def precision(self) -> str:
        return self.quantize or ("fp16" if self.fp16 else "fp32")

    def validate(self) -> None:
        """Raises InputError: a size that is not a multiple of 16, fp16 with int8, an unknown quantisation."""
        w, h = self.size
        if w < 32 or h < 32 or w % 16 or h % 16 or max(w, h) > MAX_SIDE:
            raise InputError(f"sample size {w}x{h}: both sides must be multiples of 16, from 32 to {MAX_SIDE}")
        if self.quantize is not None and self.quantize not in QUANTIZE:
            raise InputError(f"--quantize {self.quantize!r}: use {', '.join(QUANTIZE)}")
        if self.fp16 and self.quantize:
            raise InputError("--fp16 and --quantize int8 exclude each other: choose one precision")
        if self.tolerance is not None and not self.tolerance > 0:
            raise InputError(f"--tolerance {self.tolerance}: give a positive number")


@dataclass
class ExportResult:
    """What :func:`export_onnx` wrote and measured."""

    path: Path
    files: list[Path]
    info: OnnxPredictorInfo
    parity: ParityReport
    seconds: dict[str, float] = field(default_factory=dict)
    fixed_size_reason: str | None = None

    @property
    def bytes(self) -> int:
        return sum(p.stat().st_size for p in self.files if p.suffix != ".json")


# ============================================================================================= helpers
@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
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


class _HalfPrecision(nn.Module):
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
            with _quiet_exporter():
                prog = torch.onnx.export(probe, (torch.randn(2, 4),), dynamo=True, opset_version=opset)
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
        import onnxruntime as ort

        raise InputError(
            f"--opset {opset}: the installed exporter (torch {torch.__version__}) and onnxruntime "
            f"{ort.__version__} cannot produce and run it ({problem}); 18 and 20 (the default) are the safe choices"
        )


def source_digests(files: dict[str, Path | str]) -> dict[str, dict[str, str]]:
    """Role → ``{"path", "sha256"}`` of the checkpoints an export came from (a folder: the digest of its
    files' digests, in name order).

    Raises:
        InputError: a file that cannot be read.
    """
    out = {}
    for role, f in files.items():
        p = Path(f)
        try:
            out[role] = {"path": str(p), "sha256": _digest(p)}
        except OSError as e:
            raise InputError(f"cannot read {p}: {e.strerror or e}") from None
    return out


def _digest(p: Path) -> str:
    import hashlib

    if not p.is_dir():
        return sha256_file(p)
    h = hashlib.sha256()
    for child in sorted(c for c in p.rglob("*") if c.is_file()):
        h.update(f"{child.relative_to(p).as_posix()}\0{sha256_file(child)}\n".encode())
    return h.hexdigest()


def _export_program(module: nn.Module, example: tuple[torch.Tensor, ...], config: ExportConfig, names: tuple[str, ...],
                    dynamic: bool) -> Any:  # fmt: skip
    dynamic_shapes = None
    if dynamic:
        from torch.export import Dim

        batch = Dim("batch", min=1, max=64)
        ph, pw = Dim("ph", min=2, max=512), Dim("pw", min=2, max=512)
        spec = {0: batch, 2: 16 * ph, 3: 16 * pw}
        dynamic_shapes = {"img0": spec, "img1": spec}
    with _quiet_exporter(), torch.no_grad():
        return torch.onnx.export(
            module, example, dynamo=True, opset_version=config.opset, input_names=list(INPUT_NAMES),
            output_names=list(names), dynamic_shapes=dynamic_shapes, optimize=True, verbose=False,
        )  # fmt: skip


def _tidy_graph(model: Any, dynamic: bool) -> None:
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


def _set_metadata(path: Path, info: OnnxPredictorInfo) -> None:
    """Rewrite the graph file's metadata (external weights are left where they are)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    props = {p.key: p.value for p in model.metadata_props}
    props[METADATA_KEY] = info.to_json()
    del model.metadata_props[:]
    for k, v in props.items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(path))


def _quantize_int8(src: Path, dst: Path) -> None:
    from onnxruntime.quantization import QuantType, quantize_dynamic

    external = src.with_name(src.name + ".data").exists() and os.path.getsize(src.with_name(src.name + ".data")) > 4 * (
        EXTERNAL_DATA_BYTES
    )  # int8 weights are 4× smaller: external data only when they would still pass the limit
    with _quiet_exporter():
        logging.disable(logging.WARNING)  # ORT's quantiser warns on the root logger ("consider pre-processing")
        try:
            quantize_dynamic(
                str(src), str(dst), weight_type=QuantType.QInt8, per_channel=True, use_external_data_format=external
            )
        finally:
            logging.disable(logging.NOTSET)


def _run_ort(path: Path, images: tuple[torch.Tensor, torch.Tensor]) -> tuple[list[Any], str]:
    from .onnx_runtime import ORT_LOG_SEVERITY, _import_ort

    ort = _import_ort()  # and onnxruntime's own log silenced
    so = ort.SessionOptions()
    so.log_severity_level = ORT_LOG_SEVERITY
    sess = ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])
    feeds = {n: t.numpy() for n, t in zip(INPUT_NAMES, images)}
    return sess.run(None, feeds), sess.get_providers()[0]


# ============================================================================================= export
def export_onnx(
    predictor: PairPredictor,
    out: Path | str,
    config: ExportConfig | None = None,
    *,
    sources: dict[str, Path | str] | None = None,
    on_step: Callable[[str], None] | None = None,
) -> ExportResult:
    """Export ``predictor`` to ``out`` (``.onnx``), parity-check it, and keep it only if it agrees.

    Args:
        predictor: the torch predictor (any device: a CPU float32 copy is traced when it is on another one).
        out: the ``.onnx`` path; ``<out>.data`` beside it for models over 2 GB; ``<stem>.parity.json``.
        config: the export settings.
        sources: the checkpoints it was built from, by role (their sha256 go into the metadata).
        on_step: called with each step's name (``"export"``, ``"check"``, ``"quantize"``, ``"parity"``).

    Returns:
        The files written, the metadata, the parity report and each step's seconds.

    Raises:
        InputError: bad settings, an opset the installed exporter cannot produce, an unreadable checkpoint.
        OutputPathError: an output that cannot be written (checked first; a write that fails later too).
        ExportError: the exporter or ``onnx.checker`` failed, or the graph has nodes the runtime refuses.
        ParityError: onnxruntime and torch disagree beyond the tolerance (exit 3); nothing is kept.
    """
    config = config or ExportConfig()
    config.validate()
    out = Path(out)
    if out.suffix.lower() != ".onnx":
        raise InputError(f"-o {out}: the output must end in .onnx")
    parity_path = out.with_name(out.stem + ".parity.json")
    for p in (out, out.with_name(out.name + ".data"), parity_path):
        check_writable(p)
    check_opset(config.opset)
    digests = source_digests(sources or {})
    # Trace a CPU float32 module in eval mode; copy only when the caller's is elsewhere (the full model is 2.9 GB)
    on_cpu = all(p.device.type == "cpu" and p.dtype == torch.float32 for p in predictor.parameters())
    was_training = predictor.training
    predictor = predictor.eval() if on_cpu else copy.deepcopy(predictor).to("cpu", torch.float32).eval()
    try:
        return _export(predictor, out, parity_path, config, digests, on_step)
    except OSError as e:  # a full disk, a folder that refuses files although os.access allowed them (/sys)
        raise OutputPathError(f"cannot write {out}: {e.strerror or e}") from None
    finally:
        if on_cpu:
            predictor.train(was_training)


def _export(
    predictor: PairPredictor,
    out: Path,
    parity_path: Path,
    config: ExportConfig,
    digests: dict[str, dict[str, str]],
    on_step: Callable[[str], None] | None,
) -> ExportResult:
    """:func:`export_onnx` once the settings are checked. Every OSError it raises is a write into the output's
    folder (the caller reports it as such); nothing is left behind when it raises."""
    import onnx

    step = on_step or (lambda name: None)
    seconds: dict[str, float] = {}
    module: nn.Module = _HalfPrecision(predictor) if config.fp16 else predictor
    names = predictor.output_names
    w, h = config.size
    images = sample_pair(config.size)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        # ---- trace and translate
        step("export")
        t0 = time.perf_counter()
        fixed_reason = None
        dynamic = config.dynamic
        if dynamic:
            # batch ≥ 2 and H ≠ W in the example: size-1 and equal dims get specialised/unified by the tracer
            eh = h if h != w else h - 16
            example = (torch.rand(2, 3, eh, w), torch.rand(2, 3, eh, w))
            try:
                prog = _export_program(module, example, config, names, dynamic=True)
            except Exception as e:  # noqa: BLE001 - fall back to the fixed size, and say why
                fixed_reason = f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"
                logger.warning("dynamic-size export failed (%s); exporting the fixed size %dx%d", fixed_reason, w, h)
                dynamic = False
        if not dynamic:
            try:
                prog = _export_program(module, images, config, names, dynamic=False)
            except Exception as e:  # noqa: BLE001
                detail = " ".join(str(e).split())[:500]
                raise ExportError(f"the ONNX exporter failed: {type(e).__name__}: {detail}") from None
        seconds["export"] = time.perf_counter() - t0
        _tidy_graph(prog.model, dynamic)
        n_bytes = sum(p.numel() * p.element_size() for p in module.parameters())
        external = n_bytes > EXTERNAL_DATA_BYTES
        fp32_path = tmp / out.name
        with _quiet_exporter():
            prog.save(str(fp32_path), external_data=external)
        del prog
        info = OnnxPredictorInfo(
            precision=config.precision, dynamic=dynamic, size=(w, h), network=predictor.network_name(),
            fusion=predictor.fusion_name(), fusion_enabled=predictor.fusion_enabled, desc_dim=predictor.desc_dim,
            gaussian_head=predictor.has_gaussian_head, dino=_dino_info(predictor), opset=config.opset,
            outputs={n: OUTPUT_MEANINGS[n] for n in names}, sources=digests,
            config=_config_dict(predictor), macsplat_version=__version__,
        )  # fmt: skip
        _set_metadata(fp32_path, info)

        # ---- check, quantise
        step("check")
        t0 = time.perf_counter()
        try:
            onnx.checker.check_model(str(fp32_path))
        except onnx.checker.ValidationError as e:
            raise ExportError(f"onnx.checker rejected the exported model: {' '.join(str(e).split())[:500]}") from None
        seconds["check"] = time.perf_counter() - t0
        final = fp32_path
        if config.quantize == "int8":
            step("quantize")
            t0 = time.perf_counter()
            qdir = tmp / "int8"
            qdir.mkdir()
            final = qdir / out.name
            _quantize_int8(fp32_path, final)
            _set_metadata(final, info)
            seconds["quantize"] = time.perf_counter() - t0

        # ---- parity: onnxruntime against the fp32 torch predictor
        step("parity")
        t0 = time.perf_counter()
        with torch.inference_mode():
            ref = predictor(*images)
        got, provider = _run_ort(final, images)
        tol = config.tolerance if config.tolerance is not None else PARITY_TOLERANCE[config.precision]
        parity = ParityReport(compare_outputs(names, got, ref, tol), tol, config.precision, (w, h), provider)
        seconds["parity"] = time.perf_counter() - t0
        info.parity = parity.to_dict()
        if not parity.ok:
            bad = [r for r in parity.rows if not r["ok"]]
            raise ParityError(
                f"parity check failed: onnxruntime differs from torch on {', '.join(r['output'] for r in bad)} "
                f"(worst {bad[0]['output']}: {bad[0]['max_rel']:.3g} of its range, tolerance {tol:g}); "
                "no file was kept",
                parity,
            )
        try:  # a file the runtime would refuse is not written (and ALLOWED_OPS cannot rot unnoticed)
            check_graph(onnx.load(str(final), load_external_data=False), out.name)
        except OnnxPredictorError as e:
            raise ExportError(
                f"torch {torch.__version__}'s exporter wrote a graph macsplat's ONNX runtime would refuse ({e}); "
                "no file was kept"
            ) from None
        _set_metadata(final, info)
        (final.parent / parity_path.name).write_text(json.dumps(parity.to_dict(), indent=1) + "\n")

        # ---- move into place: weights first, the graph that names them last
        produced = [final.with_name(final.name + ".data"), final.parent / parity_path.name, final]
        written: list[Path] = []
        try:
            for src in produced:
                if src.exists():
                    dst = out.parent / src.name
                    os.replace(src, dst)
                    written.append(dst)
        except BaseException:
            for dst in written:  # no new weights or parity file without the graph that goes with them
                with contextlib.suppress(OSError):
                    dst.unlink()
            raise
        stale = out.with_name(out.name + ".data")
        if stale not in written and stale.exists():
            stale.unlink()  # an earlier, larger export's weights: this graph does not use them
        return ExportResult(out, written, info, parity, seconds, fixed_reason)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _dino_info(predictor: PairPredictor) -> dict[str, Any] | None:
    if not predictor.fusion_enabled or predictor.dino is None:
        return None
    c = predictor.dino.config
    return {"name": c.name, "patch_size": c.patch_size, "embed_dim": c.embed_dim}


def _config_dict(predictor: PairPredictor) -> dict[str, Any]:
    from .predictor_io import predictor_config

    try:
        return predictor_config(predictor)  # type: ignore[return-value]
    except Exception:  # noqa: BLE001 - a stand-in backbone without a config: informational only
        return {}
