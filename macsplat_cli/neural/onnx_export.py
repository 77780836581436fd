"""Export a :class:`~.predictor.PairPredictor` to ONNX, check it against torch, and keep it only if it agrees.

:func:`export_onnx` traces ``PairPredictor.forward`` with torch's ``torch.export``-based exporter
(RoPE, attention and the DPT heads lower to standard ONNX ops), with the batch and the image height
and width dynamic (``16·k``) — falling back to the sample pair's fixed size when the exporter cannot keep
them symbolic — writes :class:`~.onnx_format.OnnxPredictorInfo` into the model's metadata, runs
``onnx.checker``, optionally quantises it (onnxruntime's dynamic int8 quantisation), and runs the
**parity check**: onnxruntime and the fp32 torch predictor on the caller's sample pair (the command's is a
synthetic room, :func:`macsplat_cli.datasets.synthetic.sample.sample_pair`), each output's error
printed and written beside the file (``<stem>.parity.json``). An output beyond the tolerance fails
the export (:class:`~.onnx_format.ParityError`, exit 3); so does a node the runtime would refuse
(:func:`~.onnx_format.check_graph`; :class:`ExportError`). The steps themselves (trace, tidy, metadata,
quantise) are in :mod:`.onnx_graph`.

Everything is written into a temporary folder beside the output and moved into place at the end:
a failure, or an interrupt, leaves no partial file; a write that fails (a full disk, a folder that refuses
files although ``os.access`` allowed them) is an :class:`~macsplat_cli.errors.OutputPathError` (exit 2).
Models over 2 GB (ViT-L MASt3R in fp32) keep their weights in ``<name>.onnx.data`` beside the graph
(ONNX's external-data format).
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable
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
    OUTPUT_MEANINGS,
    PARITY_TOLERANCE,
    OnnxPredictorError,
    OnnxPredictorInfo,
    ParityError,
    ParityReport,
    check_graph,
    compare_outputs,
)
from .onnx_graph import (
    EXTERNAL_DATA_BYTES,
    HalfPrecision,
    check_opset,
    quantize_int8,
    quiet_exporter,
    set_metadata,
    tidy_graph,
    trace_program,
)
from .predictor import PairPredictor

__all__ = [
    "ExportConfig",
    "ExportError",
    "ExportResult",
    "check_sample",
    "export_onnx",
    "source_digests",
]

logger = logging.getLogger(__name__)

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
    sample: tuple[torch.Tensor, torch.Tensor],
    sources: dict[str, Path | str] | None = None,
    on_step: Callable[[str], None] | None = None,
) -> ExportResult:
    """Export ``predictor`` to ``out`` (``.onnx``), parity-check it, and keep it only if it agrees.

    Args:
        predictor: the torch predictor (any device: a CPU float32 copy is traced when it is on another one).
        out: the ``.onnx`` path; ``<out>.data`` beside it for models over 2 GB; ``<stem>.parity.json``.
        config: the export settings.
        sample: the pair a fixed-size export is traced at and the parity check runs on, photo-like (the
            command renders a synthetic room, ``datasets.synthetic.sample.sample_pair``): float32 RGB in
            [0, 1] at ``config.size``. ``[1, 3, H, W]`` each
        sources: the checkpoints it was built from, by role (their sha256 go into the metadata).
        on_step: called with each step's name (``"export"``, ``"check"``, ``"quantize"``, ``"parity"``).

    Returns:
        The files written, the metadata, the parity report and each step's seconds.

    Raises:
        InputError: bad settings, a sample pair of another size, an opset the installed exporter cannot
            produce, an unreadable checkpoint.
        OutputPathError: an output that cannot be written (checked first; a write that fails later too).
        ExportError: the exporter or ``onnx.checker`` failed, or the graph has nodes the runtime refuses.
        ParityError: onnxruntime and torch disagree beyond the tolerance (exit 3); nothing is kept.
    """
    config = config or ExportConfig()
    config.validate()
    check_sample(sample, config.size)
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
        return _export(predictor, out, parity_path, config, digests, on_step, sample)
    except OSError as e:  # a full disk, a folder that refuses files although os.access allowed them (/sys)
        raise OutputPathError(f"cannot write {out}: {e.strerror or e}") from None
    finally:
        if on_cpu:
            predictor.train(was_training)


def check_sample(sample: tuple[torch.Tensor, torch.Tensor], size: tuple[int, int]) -> None:
    """Raises InputError: ``sample`` is not two float32 ``[1, 3, H, W]`` tensors at ``size = (W, H)``."""
    w, h = size
    pair = tuple(sample) if isinstance(sample, (tuple, list)) else ()
    if len(pair) != 2 or not all(
        isinstance(t, torch.Tensor) and t.dtype == torch.float32 and tuple(t.shape) == (1, 3, h, w) for t in pair
    ):
        got = [f"{list(t.shape)} {t.dtype}" if isinstance(t, torch.Tensor) else type(t).__name__ for t in pair]
        raise InputError(f"the sample pair must be two float32 [1, 3, {h}, {w}] tensors (size {w}x{h}); got {got}")


def _export(
    predictor: PairPredictor,
    out: Path,
    parity_path: Path,
    config: ExportConfig,
    digests: dict[str, dict[str, str]],
    on_step: Callable[[str], None] | None,
    images: tuple[torch.Tensor, torch.Tensor],
) -> ExportResult:
    """:func:`export_onnx` once the settings are checked. Every OSError it raises is a write into the output's
    folder (the caller reports it as such); nothing is left behind when it raises."""
    step = on_step or (lambda name: None)
    seconds: dict[str, float] = {}
    module: nn.Module = HalfPrecision(predictor) if config.fp16 else predictor
    names = predictor.output_names
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        # ---- trace and translate
        step("export")
        t0 = time.perf_counter()
        prog, dynamic, fixed_reason = _trace(module, images, config, names)
        seconds["export"] = time.perf_counter() - t0
        tidy_graph(prog.model, dynamic)
        n_bytes = sum(p.numel() * p.element_size() for p in module.parameters())
        external = n_bytes > EXTERNAL_DATA_BYTES
        fp32_path = tmp / out.name
        with quiet_exporter():
            prog.save(str(fp32_path), external_data=external)
        del prog
        info = _info(predictor, config, dynamic, names, digests)
        set_metadata(fp32_path, info)

        final = _check_and_quantize(fp32_path, tmp, config, info, step, seconds)
        parity = _parity(predictor, final, images, config, names, step, seconds)
        info.parity = parity.to_dict()
        _check_runtime_accepts(final, out.name)
        set_metadata(final, info)
        (final.parent / parity_path.name).write_text(json.dumps(parity.to_dict(), indent=1) + "\n")
        written = _move_into_place(final, out, parity_path.name)
        return ExportResult(out, written, info, parity, seconds, fixed_reason)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _trace(
    module: nn.Module, images: tuple[torch.Tensor, torch.Tensor], config: ExportConfig, names: tuple[str, ...]
) -> tuple[Any, bool, str | None]:
    """``(program, dynamic, why the dynamic export failed)``: the dynamic export when asked for and the exporter
    can keep the sizes symbolic, else the fixed size traced at the sample pair."""
    w, h = config.size
    fixed_reason = None
    if config.dynamic:
        # batch ≥ 2 and H ≠ W in the example: size-1 and equal dims get specialised/unified by the tracer
        eh = h if h != w else h - 16
        example = (torch.rand(2, 3, eh, w), torch.rand(2, 3, eh, w))
        try:
            return trace_program(module, example, config.opset, names, dynamic=True), True, None
        except Exception as e:  # noqa: BLE001 - fall back to the fixed size, and say why
            fixed_reason = f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"
            logger.warning("dynamic-size export failed (%s); exporting the fixed size %dx%d", fixed_reason, w, h)
    try:
        return trace_program(module, images, config.opset, names, dynamic=False), False, fixed_reason
    except Exception as e:  # noqa: BLE001
        detail = " ".join(str(e).split())[:500]
        raise ExportError(f"the ONNX exporter failed: {type(e).__name__}: {detail}") from None


def _info(
    predictor: PairPredictor,
    config: ExportConfig,
    dynamic: bool,
    names: tuple[str, ...],
    digests: dict[str, dict[str, str]],
) -> OnnxPredictorInfo:
    """The metadata written into the file (its ``parity`` is filled in once the check has run)."""
    w, h = config.size
    return OnnxPredictorInfo(
        precision=config.precision, dynamic=dynamic, size=(w, h), network=predictor.network_name(),
        fusion=predictor.fusion_name(), fusion_enabled=predictor.fusion_enabled, desc_dim=predictor.desc_dim,
        gaussian_head=predictor.has_gaussian_head, dino=_dino_info(predictor), opset=config.opset,
        outputs={n: OUTPUT_MEANINGS[n] for n in names}, sources=digests,
        config=_config_dict(predictor), macsplat_version=__version__,
    )  # fmt: skip


def _check_and_quantize(
    fp32_path: Path,
    tmp: Path,
    config: ExportConfig,
    info: OnnxPredictorInfo,
    step: Callable[[str], None],
    seconds: dict[str, float],
) -> Path:
    """``onnx.checker`` on the float32 file, then the int8 quantisation when asked for; the file to keep."""
    import onnx

    step("check")
    t0 = time.perf_counter()
    try:
        onnx.checker.check_model(str(fp32_path))
    except onnx.checker.ValidationError as e:
        raise ExportError(f"onnx.checker rejected the exported model: {' '.join(str(e).split())[:500]}") from None
    seconds["check"] = time.perf_counter() - t0
    if config.quantize != "int8":
        return fp32_path
    step("quantize")
    t0 = time.perf_counter()
    qdir = tmp / "int8"
    qdir.mkdir()
    final = qdir / fp32_path.name
    quantize_int8(fp32_path, final)
    set_metadata(final, info)
    seconds["quantize"] = time.perf_counter() - t0
    return final


def _parity(
    predictor: PairPredictor,
    final: Path,
    images: tuple[torch.Tensor, torch.Tensor],
    config: ExportConfig,
    names: tuple[str, ...],
    step: Callable[[str], None],
    seconds: dict[str, float],
) -> ParityReport:
    """onnxruntime on ``final`` against the fp32 torch predictor on the sample pair.

    Raises:
        ParityError: an output beyond the tolerance.
    """
    step("parity")
    t0 = time.perf_counter()
    with torch.inference_mode():
        ref = predictor(*images)
    got, provider = _run_ort(final, images)
    tol = config.tolerance if config.tolerance is not None else PARITY_TOLERANCE[config.precision]
    w, h = config.size
    parity = ParityReport(compare_outputs(names, got, ref, tol), tol, config.precision, (w, h), provider)
    seconds["parity"] = time.perf_counter() - t0
    if not parity.ok:
        bad = [r for r in parity.rows if not r["ok"]]
        raise ParityError(
            f"parity check failed: onnxruntime differs from torch on {', '.join(r['output'] for r in bad)} "
            f"(worst {bad[0]['output']}: {bad[0]['max_rel']:.3g} of its range, tolerance {tol:g}); "
            "no file was kept",
            parity,
        )
    return parity


def _check_runtime_accepts(final: Path, name: str) -> None:
    """A file the runtime would refuse is not written (and ``ALLOWED_OPS`` cannot rot unnoticed).

    Raises:
        ExportError: a node outside the runtime's allow-list, a subgraph, a non-float output.
    """
    import onnx

    try:
        check_graph(onnx.load(str(final), load_external_data=False), name)
    except OnnxPredictorError as e:
        raise ExportError(
            f"torch {torch.__version__}'s exporter wrote a graph macsplat's ONNX runtime would refuse ({e}); "
            "no file was kept"
        ) from None


def _move_into_place(final: Path, out: Path, parity_name: str) -> list[Path]:
    """Move the weights, the parity report and the graph beside ``out`` — the graph that names the weights
    last — and return them; on a failure, none of them stays."""
    produced = [final.with_name(final.name + ".data"), final.parent / parity_name, final]
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
    return written


def _dino_info(predictor: PairPredictor) -> dict[str, Any] | None:
    if not predictor.fusion_enabled or predictor.dino is None:
        return None
    c = predictor.dino.config
    return {"name": c.name, "patch_size": c.patch_size, "embed_dim": c.embed_dim}


def _config_dict(predictor: PairPredictor) -> dict[str, Any]:
    from .predictor_io import predictor_config

    try:
        return predictor_config(predictor)
    except Exception:  # noqa: BLE001 - a stand-in backbone without a config: informational only
        return {}
