"""``macsplat bench``: the evaluation over a grid of settings; time vs quality and its Pareto front."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, TypeVar

import typer

from ..presets import DEFAULT_MATCHER
from ._app import app
from ._common import QuietOpt, VerboseOpt, command_context, err_console, escape, out_console
from ._options import (
    DeviceOpt,
    DinoOpt,
    FusionOpt,
    GaussianHeadOpt,
    PrecisionOpt,
    RefineGridOpt,
    WeightsOpt,
    choice,
    neural_options,
    parse_refine_list,
)
from .eval import (
    INTRINSICS,
    AssignmentOpt,
    CasesOpt,
    ContextViewsOpt,
    DataOpt,
    IntrinsicsOpt,
    LayoutOpt,
    MaxPairsOpt,
    MaxTargetsOpt,
    RichProgress,
    ScannetSplitOpt,
    ScenesOpt,
    SeedOpt,
    Splatt3rOpt,
    SplitByOpt,
    SplitOpt,
    case_spec,
)

logger = logging.getLogger("macsplat_cli.cli.bench")


T = TypeVar("T")


def _list(text: str, kind: Callable[[str], T], option: str) -> list[T]:
    """Comma-separated values of ``kind`` (its name in the message of a bad one)."""
    return [v for v in _values(text, kind, option, allow_default=False) if v is not None]


def _values(text: str, kind: Callable[[str], T], option: str, *, allow_default: bool = True) -> list[T | None]:
    """Comma-separated values of ``kind``; ``default`` stands for None where allowed."""
    from ..errors import InputError

    out: list[T | None] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        if allow_default and part.lower() == "default":
            out.append(None)
            continue
        try:
            out.append(kind(part))
        except ValueError:
            raise InputError(f"{option} {text!r}: {part!r} is not a {getattr(kind, '__name__', kind)}") from None
    if not out:
        raise InputError(f"{option}: give at least one value")
    return out


@app.command("bench")
def bench_command(
    ctx: typer.Context,
    data: DataOpt,
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for bench.md, bench.png, bench.json, runs/.")] = Path(
        "bench"
    ),
    backend: Annotated[str, typer.Option("--backend", help="Backends, comma-separated.")] = "classical",
    size: Annotated[str, typer.Option("--size", help="Working sizes, comma-separated.")] = "384,512",
    conf_threshold: Annotated[
        str, typer.Option("--conf-threshold", help="Matching thresholds τ, comma-separated ('default' allowed).")
    ] = "default",
    refine: RefineGridOpt = None,
    quality: Annotated[
        str, typer.Option("--quality", help="Presets (fast, balanced, best), comma-separated; each as reconstruct's.")
    ] = "balanced",
    eval_size: Annotated[
        int | None,
        typer.Option(
            "--eval-size", min=64, help="Compare all settings' views at this long side (default: the largest --size)."
        ),
    ] = None,
    metric: Annotated[
        str, typer.Option("--metric", help="Quality axis: psnr, psnr_masked, ssim, auc@10, rotation_error_deg, ...")
    ] = "psnr",
    split: SplitOpt = "all",
    layout: LayoutOpt = "auto",
    scannetpp_split: ScannetSplitOpt = "nvs_sem_val",
    scenes: ScenesOpt = None,
    cases: CasesOpt = None,
    intrinsics: IntrinsicsOpt = "given",
    max_pairs: MaxPairsOpt = 2,
    max_targets: MaxTargetsOpt = 2,
    split_by: SplitByOpt = "auto",
    assignment: AssignmentOpt = "bin",
    seed: SeedOpt = 0,
    context_views: ContextViewsOpt = 2,
    splatt3r_compatible: Splatt3rOpt = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the bench as JSON on stdout.")] = False,
    matcher: Annotated[
        str,
        typer.Option(
            "--matcher",
            help="Matchers of the classical backend (sift, auto, aliked: see reconstruct), comma-separated.",
        ),
    ] = DEFAULT_MATCHER,
    weights: WeightsOpt = None,
    gaussian_head: GaussianHeadOpt = None,
    dino: DinoOpt = None,
    fusion: FusionOpt = None,
    device: DeviceOpt = "cpu",
    precision: PrecisionOpt = "fp32",
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Run the evaluation over a grid of settings; report time vs quality and the Pareto front.

    Every combination of --backend, --size, --conf-threshold, --refine, --quality and --matcher is evaluated on
    the same cases (with --context-views N, N context photos each). Writes a Markdown table (bench.md), a plot
    (bench.png), bench.json, and each setting's full results under runs/.

    [bold]Example[/]

      macsplat bench --data co3d_apple/ --size 256,384,512 --refine 0,50 --metric psnr
    """
    with command_context(ctx, verbose, quiet) as state:
        from .. import evaluation
        from ..evaluation.bench import bench_json, bench_markdown
        from ..presets import MATCHERS, QUALITIES

        spec = evaluation.BenchSpec(
            cases=case_spec(
                data, layout=layout, scannetpp_split=scannetpp_split, scenes=scenes, cases=cases, split=split,
                split_by=split_by, assignment=assignment, max_pairs=max_pairs, max_targets=max_targets, seed=seed,
                context_views=context_views,
            ),
            out=out, backends=_list(backend, str, "--backend"), sizes=_list(size, int, "--size"),
            taus=_values(conf_threshold, float, "--conf-threshold"), steps=parse_refine_list(refine),
            qualities=[choice("--quality", q, QUALITIES, sep=", ") for q in _list(quality, str, "--quality")],
            matchers=[choice("--matcher", m, MATCHERS, sep=", ") for m in _list(matcher, str, "--matcher")],
            neural=neural_options(weights, gaussian_head, dino, fusion, device, precision), metric=metric,
            eval_size=eval_size, intrinsics=choice("--intrinsics", intrinsics, INTRINSICS),
            splatt3r_compatible=splatt3r_compatible,
        )  # fmt: skip
        rows = evaluation.benchmark(spec, RichProgress(state.quiet))
        if not state.quiet:
            from rich.markdown import Markdown

            err_console.print(Markdown(bench_markdown(rows, metric)))
            err_console.print(
                escape(f"wrote {out / 'bench.md'}, {out / 'bench.png'}, {out / 'bench.json'}"), highlight=False
            )
        if json_out:
            out_console.print_json(json.dumps(bench_json(rows, metric)))
