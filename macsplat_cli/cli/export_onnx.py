"""``macsplat export-onnx``: the predictor as one ONNX file, parity-checked against torch."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Any

import typer

from ._app import app
from ._common import (
    QuietOpt,
    StageProgress,
    VerboseOpt,
    check_no_clobber,
    command_context,
    err_console,
    escape,
    out_console,
)
from ._options import DinoOpt, FusionOpt, GaussianHeadOpt, WeightsOpt

logger = logging.getLogger("macsplat_cli.cli.export_onnx")

_STEPS = {
    "load": "loading checkpoints",
    "export": "tracing → ONNX",
    "check": "onnx.checker",
    "quantize": "int8 quantisation",
    "parity": "parity vs torch",
}

_OPTION_OF = {"weights": "--weights", "gaussian_head": "--gaussian-head", "dino": "--dino", "fusion": "--fusion"}


def parse_size(text: str) -> tuple[int, int]:
    """``512`` (long side, 4:3 landscape → 512x384) or ``WxH``; both multiples of 16, at least 32."""
    from ..errors import InputError

    t = text.strip().lower()
    try:
        if "x" in t:
            w, h = (int(v) for v in t.split("x"))
        else:
            w = int(t)
            h = max(32, int(round(w * 3 / 4 / 16)) * 16)
    except ValueError:
        raise InputError(f"--size {text!r}: give the long side (e.g. 512) or WIDTHxHEIGHT (e.g. 512x384)") from None
    if w < 32 or h < 32 or w % 16 or h % 16:
        raise InputError(f"--size {text!r}: both sides must be multiples of 16, at least 32")
    return w, h


@app.command("export-onnx")
def export_onnx_command(
    ctx: typer.Context,
    output: Annotated[Path, typer.Option("--output", "-o", help="The ONNX file to write (.onnx).")],
    weights: WeightsOpt = None,
    checkpoint: Annotated[
        Path | None,
        typer.Option("--checkpoint", metavar="PATH", help="A macsplat training checkpoint (runs/x/best.pt)."),
    ] = None,
    gaussian_head: GaussianHeadOpt = None,
    dino: DinoOpt = None,
    fusion: FusionOpt = None,
    size: Annotated[
        str,
        typer.Option(
            "--size", metavar="N|WxH", help="Sample pair for tracing and the parity check: long side (4:3) or WxH."
        ),
    ] = "512",
    opset: Annotated[int, typer.Option("--opset", help="ONNX opset.")] = 20,
    fp16: Annotated[bool, typer.Option("--fp16", help="Compute in half precision (float32 in and out; GPUs).")] = False,
    quantize: Annotated[
        str | None, typer.Option("--quantize", metavar="int8", help="Dynamic int8 quantisation (CPUs).")
    ] = None,
    fixed_size: Annotated[
        bool, typer.Option("--fixed-size", help="Export for the --size only (default: any H, W multiple of 16).")
    ] = False,
    tolerance: Annotated[
        float | None,
        typer.Option(
            "--tolerance",
            help="Parity bound, relative to each output's range [default: 1e-3 fp32, 3e-2 fp16, 0.25 int8].",
        ),
    ] = None,
    json_out: Annotated[
        bool, typer.Option("--json", help="Print the result (metadata, parity) as JSON on stdout.")
    ] = False,
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Export the predictor (MASt3R backbone [+ fusion] [+ Gaussian head]) to ONNX, check it with onnxruntime
    against torch on a sample pair, and keep it only if every output agrees (exit 3 otherwise).

    The file runs in place of the checkpoints: [bold]macsplat reconstruct A B -o s.ply --backend neural
    --weights predictor.onnx[/]."""
    with command_context(ctx, verbose, quiet) as state:
        from ..neural.onnx_export import ExportConfig

        files = _sources(weights, checkpoint, gaussian_head, dino, fusion)
        config = ExportConfig(
            size=parse_size(size), opset=opset, fp16=fp16, quantize=quantize.strip().lower() if quantize else None,
            dynamic=not fixed_size, tolerance=tolerance,
        )  # fmt: skip
        config.validate()
        _check_outputs(output, files, checkpoint is not None)
        result = _export(output, config, files, checkpoint is not None, quiet=state.quiet)
        if not state.quiet:
            _summary(result)
        if json_out:
            from .._json import to_jsonable

            doc = {"files": [str(p) for p in result.files], "bytes": result.bytes, "seconds": result.seconds,
                   "metadata": to_jsonable(result.info)}  # fmt: skip
            out_console.print_json(json.dumps(doc, allow_nan=False))


def _sources(
    weights: Path | None, checkpoint: Path | None, gaussian_head: Path | None, dino: Path | None, fusion: Path | None
) -> dict[str, Path]:
    """The torch checkpoints to export, by role (``weights``: ``--weights`` or ``--checkpoint``)."""
    from ..errors import InputError
    from ..neural.onnx_runtime import is_onnx_file
    from ..neural.predictor import MISSING_WEIGHTS_HELP

    if checkpoint is not None and weights is not None:
        raise InputError("--checkpoint and --weights both name the backbone: give one")
    source = checkpoint if checkpoint is not None else weights
    if is_onnx_file(source):
        raise InputError(f"{source} is already an ONNX file: export from the torch checkpoints")
    if source is None and gaussian_head is None:
        raise InputError(MISSING_WEIGHTS_HELP.replace("--backend neural needs", "export-onnx needs"))
    return {k: v for k, v in (("weights", source), ("gaussian_head", gaussian_head), ("dino", dino),
                              ("fusion", fusion)) if v is not None}  # fmt: skip


def _check_outputs(output: Path, files: dict[str, Path], from_checkpoint: bool) -> None:
    """Before loading gigabytes: an output that is an input (the more precise message first), then writable."""
    from .._atomic import check_writable
    from ..errors import InputError

    written = [output, output.with_name(output.name + ".data"), output.with_name(output.stem + ".parity.json")]
    check_no_clobber(
        [("-o", p) for p in written],
        [(_OPTION_OF[k] if k != "weights" or not from_checkpoint else "--checkpoint", v) for k, v in files.items()],
    )
    for p in written:  # the weights file and the parity report beside the graph too
        check_writable(p)
    if output.suffix.lower() != ".onnx":
        raise InputError(f"-o {output}: the output must end in .onnx")


def _export(output: Path, config: Any, files: dict[str, Path], from_checkpoint: bool, *, quiet: bool) -> Any:
    """Load the predictor and export it, one progress line per step; a failed parity check prints its table."""
    from ..datasets.synthetic.sample import sample_pair
    from ..neural.loading import load_pair_predictor
    from ..neural.onnx_export import export_onnx
    from ..neural.onnx_format import ParityError

    with StageProgress(disabled=quiet) as progress:
        progress.event(_STEPS["load"], "start")
        try:
            predictor = load_pair_predictor(**files)
        except BaseException:
            progress.event(_STEPS["load"], "fail")
            raise
        progress.event(_STEPS["load"], "end")
        current: list[str] = []

        def on_step(name: str) -> None:
            if current:
                progress.event(_STEPS[current.pop()], "end")
            progress.event(_STEPS[name], "start")
            current.append(name)

        try:
            sources: dict[str, Path | str] = {
                ("checkpoint" if k == "weights" and from_checkpoint else k): v for k, v in files.items()
            }
            result = export_onnx(
                predictor, output, config, sample=sample_pair(config.size), sources=sources, on_step=on_step
            )
        except BaseException as e:
            if current:
                progress.event(_STEPS[current.pop()], "fail")
            if isinstance(e, ParityError) and e.report is not None:
                progress.progress.stop()
                err_console.print(_parity_table(e.report))
            raise
        if current:
            progress.event(_STEPS[current.pop()], "end")
    return result


def _summary(result: Any) -> None:
    from rich.table import Table

    info = result.info
    t = Table(title="macsplat export-onnx", show_header=False, title_justify="left")
    t.add_column(style="bold")
    t.add_column()
    t.add_row("network", escape(info.network))
    t.add_row("fusion", escape(info.fusion))
    t.add_row("Gaussian head", "yes" if info.gaussian_head else "no")
    sizes = "any H, W multiple of 16 (dynamic batch)" if info.dynamic else f"{info.size[0]}x{info.size[1]} only"
    if result.fixed_size_reason:
        sizes += f" — the dynamic export failed: {escape(result.fixed_size_reason[:120])}"
    t.add_row("input size", sizes)
    t.add_row("precision", escape(f"{info.precision}, opset {info.opset}"))
    t.add_row("files", "\n".join(f"{escape(str(p))} ({p.stat().st_size / 1e6:,.1f} MB)" for p in result.files))
    t.add_row("time", escape(", ".join(f"{k} {v:.1f} s" for k, v in result.seconds.items())))
    err_console.print(t)
    err_console.print(_parity_table(result.parity))


def _parity_table(p: Any) -> Any:
    from rich.table import Table

    pt = Table(
        title=f"parity: onnxruntime vs torch fp32 at {p.size[0]}x{p.size[1]} (tolerance {p.tolerance:g} of range)",
        title_justify="left",
    )
    pt.add_column("output")
    pt.add_column("max abs", justify="right")
    pt.add_column("max rel", justify="right")
    pt.add_column("")
    for r in p.rows:
        mark = "[green]ok[/]" if r["ok"] else "[red]✗[/]"
        pt.add_row(escape(str(r["output"])), f"{r['max_abs']:.2e}", f"{r['max_rel']:.2e}", mark)
    return pt
