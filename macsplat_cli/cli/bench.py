"""``macsplat bench``: the evaluation over a grid of settings; time vs quality and its Pareto front."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ..presets import DEFAULT_MATCHER
from ._app import app
from ._common import QuietOpt, VerboseOpt, check_no_clobber, command_context, err_console, escape, out_console
from ._options import (
    DeviceOpt,
    DinoOpt,
    FusionOpt,
    GaussianHeadOpt,
    PrecisionOpt,
    RefineGridOpt,
    WeightsOpt,
    neural_options,
    parse_refine_list,
)
from .eval import (
    AssignmentChoice,
    AssignmentOpt,
    CasesOpt,
    ContextViewsOpt,
    DataOpt,
    IntrinsicsChoice,
    IntrinsicsOpt,
    LayoutChoice,
    LayoutOpt,
    MaxPairsOpt,
    MaxTargetsOpt,
    ScannetSplitOpt,
    ScenesOpt,
    SeedOpt,
    Splatt3rOpt,
    SplitByChoice,
    SplitByOpt,
    SplitOpt,
    engine_config,
    load_data,
    run_with_progress,
    select_cases,
)

if TYPE_CHECKING:
    from ..engine import NeuralOptions

logger = logging.getLogger("macsplat_cli.cli.bench")


def _list(text: str, kind: type, option: str, *, allow_default: bool = False) -> list:
    """Comma-separated values of ``kind``; ``default`` stands for None where allowed."""
    from ..errors import InputError

    out = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        if allow_default and part.lower() == "default":
            out.append(None)
            continue
        try:
            out.append(kind(part))
        except ValueError:
            raise InputError(f"{option} {text!r}: {part!r} is not a {kind.__name__}") from None
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
    layout: LayoutOpt = LayoutChoice.auto,
    scannetpp_split: ScannetSplitOpt = "nvs_sem_val",
    scenes: ScenesOpt = None,
    cases: CasesOpt = None,
    intrinsics: IntrinsicsOpt = IntrinsicsChoice.given,
    max_pairs: MaxPairsOpt = 2,
    max_targets: MaxTargetsOpt = 2,
    split_by: SplitByOpt = SplitByChoice.auto,
    assignment: AssignmentOpt = AssignmentChoice.bin,
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
        _bench(
            data=data, out=out, backends=_list(backend, str, "--backend"), sizes=_list(size, int, "--size"),
            taus=_list(conf_threshold, float, "--conf-threshold", allow_default=True),
            steps=parse_refine_list(refine), qualities=_list(quality, str, "--quality"), eval_size=eval_size,
            metric=metric, split=split,
            layout=layout.value,
            scannetpp_split=scannetpp_split, scenes=scenes, cases_file=cases, intrinsics=intrinsics.value,
            max_pairs=max_pairs, max_targets=max_targets, split_by=split_by.value, assignment=assignment.value,
            seed=seed, context_views=context_views, splatt3r_compatible=splatt3r_compatible, json_out=json_out,
            quiet=state.quiet, matchers=_list(matcher, str, "--matcher"),
            neural=neural_options(weights, gaussian_head, dino, fusion, device, precision),
        )  # fmt: skip


def _bench(
    *, data: Path, out: Path, backends: list[str], sizes: list[int], taus: list[float | None],
    steps: list[int | None],
    qualities: list[str], eval_size: int | None, metric: str, split: str, layout: str, scannetpp_split: str,
    scenes: str | None,
    cases_file: Path | None, intrinsics: str, max_pairs: int, max_targets: int, split_by: str, assignment: str,
    seed: int, splatt3r_compatible: bool, json_out: bool, quiet: bool, neural: NeuralOptions, context_views: int = 2,
    matchers: list[str] | None = None,
) -> None:  # fmt: skip
    import json

    from ..errors import InputError
    from ..evaluation import BACKENDS
    from ..evaluation.bench import (
        BENCH_FILES,
        METRICS,
        bench_json,
        bench_markdown,
        check_bench_outputs,
        grid,
        run_bench,
    )
    from ..evaluation.contexts import check_context_views
    from ..evaluation.result_files import ResultWriter

    if metric not in METRICS:
        raise InputError(f"--metric {metric!r}: use one of {', '.join(METRICS)}")
    unknown = [b for b in backends if b not in BACKENDS]
    if unknown:
        raise InputError(f"--backend {unknown[0]!r}: available: {', '.join(sorted(BACKENDS))}")
    if any(s < 64 for s in sizes) or any(t is not None and t < 0 for t in taus):  # --refine: parse_refine_list
        raise InputError("--size must be ≥ 64 and --conf-threshold ≥ 0")
    check_context_views(context_views, backends=backends)
    from ..presets import check_quality

    qualities = [q.strip().lower() for q in qualities]
    for q in qualities:
        check_quality(q)
    matchers = [m.strip().lower() for m in matchers or [DEFAULT_MATCHER]]
    for m in matchers:
        engine_config("classical", matcher=m).validate()
    if neural.given and "neural" not in backends:
        raise InputError(f"{', '.join(neural.given)} only apply to --backend neural")
    if "neural" in backends:  # usage errors (no weights, --dino without --fusion, ...) before any work
        engine_config("neural", neural=neural).validate()
    settings = grid(backends, sizes, taus, steps, qualities, matchers)
    check_bench_outputs(out, settings)  # every file of the bench and of each setting's run, before any work
    check_no_clobber(
        [(f"--out {out}:", out / name) for name in BENCH_FILES]
        + [(f"--out {out}:", out / "runs" / s.slug / name) for s in settings for name in ResultWriter.FILES],
        [("--cases", cases_file)],
    )
    dataset = load_data(data, layout, scannetpp_split, scenes)
    sel = select_cases(
        dataset, cases_file=cases_file, split=split, split_by=split_by, assignment=assignment,
        max_pairs=max_pairs, max_targets=max_targets, seed=seed, quiet=quiet, context_views=context_views,
    )  # fmt: skip
    if not quiet:
        each = f", {context_views} context views each" if context_views > 2 else ""
        err_console.print(
            f"{len(settings)} setting(s) × {len(sel.cases)} case(s) from {len(dataset.scenes)} scene(s){each}",
            highlight=False,
        )

    def run_fn(dataset, cases, recon, cfg, writer: ResultWriter | None, index: int):  # noqa: ANN001, ANN202
        label = f"[{index + 1}/{len(settings)}] {settings[index].slug} "
        return run_with_progress(dataset, list(cases), recon, cfg, writer, quiet, label=label)

    rows = run_bench(
        dataset, sel.cases, settings, metric=metric, intrinsics=intrinsics, eval_size=eval_size,
        splatt3r_compatible=splatt3r_compatible, out_dir=out, run_fn=run_fn,
        base=engine_config("classical", neural=neural),
    )  # fmt: skip
    if not quiet:
        from rich.markdown import Markdown

        err_console.print(Markdown(bench_markdown(rows, metric)))
        err_console.print(
            escape(f"wrote {out / 'bench.md'}, {out / 'bench.png'}, {out / 'bench.json'}"), highlight=False
        )
    if json_out:
        out_console.print_json(json.dumps(bench_json(rows, metric)))
