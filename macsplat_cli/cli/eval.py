"""``macsplat eval``: measure a backend on a data set of posed images (splits, metrics, baselines)."""

from __future__ import annotations

import json
import logging
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ..presets import DEFAULT_MATCHER
from ._app import app
from ._common import QuietOpt, VerboseOpt, check_no_clobber, command_context, err_console, escape, out_console
from ._eval_report import print_summary
from ._options import (
    DeviceOpt,
    DinoOpt,
    FusionOpt,
    GaussianHeadOpt,
    MatcherOpt,
    PrecisionOpt,
    RefineOpt,
    WeightsOpt,
    engine_config,
    neural_options,
    parse_refine,
)

if TYPE_CHECKING:
    from ..engine import EngineConfig, NeuralOptions  # noqa: F401
    from ..evaluation import CaseSelection, EvalCase, EvalDataset, EvalRun

logger = logging.getLogger("macsplat_cli.cli.eval")


class LayoutChoice(str, Enum):
    auto = "auto"
    generic = "generic"
    scannetpp = "scannetpp"
    co3d_json = "co3d-json"
    icl_nuim = "icl-nuim"
    nyu_rgbd = "nyu-rgbd"


class IntrinsicsChoice(str, Enum):
    given = "given"
    estimated = "estimated"


class SplitByChoice(str, Enum):
    auto = "auto"
    coverage = "coverage"
    angle = "angle"


class AssignmentChoice(str, Enum):
    bin = "bin"
    threshold = "threshold"


DataOpt = Annotated[
    Path,
    typer.Option(
        "--data", metavar="DIR", help="Data set folder (generic, ScanNet++, CO3D sample, ICL-NUIM/NYU RGB-D)."
    ),
]


SplitOpt = Annotated[str, typer.Option("--split", help="close, medium, wide, very-wide (comma-separated), or all.")]
LayoutOpt = Annotated[LayoutChoice, typer.Option("--layout", help="Folder layout (auto: detect it).")]
ScannetSplitOpt = Annotated[
    str, typer.Option("--scannetpp-split", help="ScanNet++: the split file to take the scenes from.")
]
ScenesOpt = Annotated[str | None, typer.Option("--scenes", help="Only these scenes (comma-separated).")]
CasesOpt = Annotated[
    Path | None,
    typer.Option("--cases", metavar="FILE", help="Explicit test cases (JSON; also Splatt3R's test_set_*.json)."),
]
IntrinsicsOpt = Annotated[
    IntrinsicsChoice,
    typer.Option("--intrinsics", help="given: pass the true intrinsics; estimated: the backend finds them."),
]
MaxPairsOpt = Annotated[
    int, typer.Option("--max-pairs", min=0, help="Context pairs per split and scene (0 = all), drawn with --seed.")
]
MaxTargetsOpt = Annotated[int, typer.Option("--max-targets", min=0, help="Targets per pair (0 = all).")]
SplitByOpt = Annotated[SplitByChoice, typer.Option("--split-by", help="Coverage (needs depth), view angle, or auto.")]
AssignmentOpt = Annotated[
    AssignmentChoice,
    typer.Option("--assignment", help="bin: each pair in its tightest split; threshold: thresholds as lower bounds."),
]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed of the pair and target draws.")]
ContextViewsOpt = Annotated[
    int,
    typer.Option(
        "--context-views",
        metavar="N",
        help="Context photos per case: the drawn pair, plus N-2 frames spread between (then around) it, never a "
        "target; N > 2 reconstructs them together (classical backend).",
    ),
]
Splatt3rOpt = Annotated[
    bool,
    typer.Option(
        "--splatt3r-compatible", help="Splatt3R's metric convention (mask-then-compare, channel-summed masked PSNR)."
    ),
]


def load_data(data: Path, layout: str, scannetpp_split: str, scenes: str | None) -> EvalDataset:
    """The data set, validated (DatasetError names the bad file)."""
    from ..evaluation import load_dataset

    names = [s.strip() for s in scenes.split(",") if s.strip()] if scenes else None
    return load_dataset(data, layout, scannetpp_split=scannetpp_split, scenes=names)


def select_cases(
    dataset: EvalDataset,
    *,
    cases_file: Path | None,
    split: str,
    split_by: str,
    assignment: str,
    max_pairs: int,
    max_targets: int,
    seed: int,
    quiet: bool,
    context_views: int = 2,
    every: int = 1,
    exclude: tuple[str, ...] = (),
) -> CaseSelection:
    """Test cases from a file or from the splits, with a spinner while coverage is computed; with more than two
    context views, each case's pair extended (:mod:`~macsplat_cli.evaluation.contexts`)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    from ..errors import DatasetError
    from ..evaluation import SplitConfig, load_cases, make_cases, parse_splits
    from ..evaluation.contexts import extend_cases
    from ..evaluation.protocol import check_context_sizes

    splits = parse_splits(split)
    if cases_file is not None:
        sel = load_cases(cases_file, dataset, every=every, exclude=exclude)
        if split.strip().lower() != "all":
            sel.cases = [c for c in sel.cases if c.split in splits]
        sel.cases, left = extend_cases(dataset, sel.cases, context_views)
        check_context_sizes(dataset, sel.cases)
    else:
        check_context_sizes(dataset)  # any frame may become a context view: before the O(N²) coverage
        cfg = SplitConfig(
            splits=splits,
            mode=split_by,  # type: ignore[arg-type]
            assignment=assignment,  # type: ignore[arg-type]
            max_pairs=max_pairs or None,
            max_targets=max_targets or None,
            seed=seed,
        )
        progress = Progress(
            TextColumn("coverage {task.description}", markup=False),  # scene names are not markup
            BarColumn(),
            MofNCompleteColumn(),
            console=err_console,
            disable=quiet,
            transient=True,
        )
        tasks: dict[str, Any] = {}

        def on_coverage(scene: str, done: int, total: int) -> None:
            if scene not in tasks:
                tasks[scene] = progress.add_task(scene, total=total)
            progress.update(tasks[scene], completed=done)

        with progress:
            sel = make_cases(dataset, cfg, on_coverage=on_coverage)
        sel.cases, left = extend_cases(dataset, sel.cases, context_views, cfg.angle_slack_deg)
    if left and not quiet:
        err_console.print(
            escape(
                f"{len(left)} case(s) left out (first: {left[0].key}): too few frames besides their targets for "
                f"{context_views} context views"
            ),
            style="yellow",
            highlight=False,
        )
    if not sel.cases and left:
        raise DatasetError(
            f"{dataset.root}: no test case can have {context_views} context views (the scenes have too few frames "
            "besides the targets); try a smaller --context-views"
        )
    if not sel.cases:
        raise DatasetError(
            f"{dataset.root}: no test case for split {split!r} (a pair needs a target, and an overlap or angle in "
            "the split's range); try --split all, --assignment threshold, or --cases FILE"
        )
    return sel


def run_with_progress(
    dataset: EvalDataset,
    cases: list[EvalCase],
    reconstructor: Any,
    config: Any,
    writer: Any,
    quiet: bool,
    label: str = "",
) -> EvalRun:
    """:func:`~macsplat_cli.evaluation.evaluate` with a progress bar; partial results stay written on Ctrl-C."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ..evaluation import evaluate

    progress = Progress(
        TextColumn(label + "{task.description:<32}", markup=False),  # case keys are not markup
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("{task.fields[last]}", markup=False),
        console=err_console,
        disable=quiet,
        transient=True,
    )
    task = progress.add_task("", total=len(cases), last="")

    def on_case(i: int, case: Any, res: Any) -> None:
        if res is None:
            progress.update(task, description=case.key)
            return
        last = {"ok": f"pose err {res.pose_error_deg:.1f}°", "failed": "failed", "error": "input error"}[res.status]
        progress.update(task, completed=i + 1, last=last)

    try:
        with progress:
            return evaluate(dataset, cases, reconstructor, config, writer=writer, on_case=on_case)
    except KeyboardInterrupt:
        if writer is not None:
            err_console.print(
                f"interrupted: the cases finished so far are in {escape(str(writer.folder))}", style="yellow"
            )
        raise


@app.command("eval")
def eval_command(
    ctx: typer.Context,
    data: DataOpt,
    split: SplitOpt = "all",
    backend: Annotated[
        str, typer.Option("--backend", help="Reconstruction backend: classical, or neural (--weights ...).")
    ] = "classical",
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for results.json, results.csv, cases.jsonl.")] = Path(
        "results"
    ),
    layout: LayoutOpt = LayoutChoice.auto,
    scannetpp_split: ScannetSplitOpt = "nvs_sem_val",
    scenes: ScenesOpt = None,
    cases: CasesOpt = None,
    size: Annotated[
        int | None,
        typer.Option("--size", min=64, help="Long side of the working images [default: 384 fast, else 512]."),
    ] = None,
    eval_size: Annotated[
        int | None,
        typer.Option("--eval-size", min=64, help="Compare views at this long side (default: --size)."),
    ] = None,
    intrinsics: IntrinsicsOpt = IntrinsicsChoice.given,
    conf_threshold: Annotated[
        float | None, typer.Option("--conf-threshold", help="Matching confidence threshold τ (default 0.04).")
    ] = None,
    refine: RefineOpt = None,
    quality: Annotated[
        str,
        typer.Option(
            "--quality",
            metavar="fast|balanced|best",
            help="The preset, as reconstruct's: working size, stages, refinement, compaction.",
        ),
    ] = "balanced",
    max_pairs: MaxPairsOpt = 5,
    max_targets: MaxTargetsOpt = 3,
    split_by: SplitByOpt = SplitByChoice.auto,
    assignment: AssignmentOpt = AssignmentChoice.bin,
    seed: SeedOpt = 0,
    context_views: ContextViewsOpt = 2,
    splatt3r_compatible: Splatt3rOpt = False,
    no_baselines: Annotated[
        bool, typer.Option("--no-baselines", help="Skip the point-cloud and copy baselines.")
    ] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON on stdout.")] = False,
    shard: Annotated[
        str | None,
        typer.Option("--shard", metavar="I/N", help="Only every N-th case from the I-th (0-based); then 'eval merge'."),
    ] = None,
    jobs: Annotated[int, typer.Option("--jobs", min=1, help="Run as this many processes (shards), then merge.")] = 1,
    protocol: Annotated[
        str | None,
        typer.Option("--protocol", metavar="NAME", help="A paper's protocol: mac-splat (see models/mac-splat.md)."),
    ] = None,
    matcher: MatcherOpt = DEFAULT_MATCHER,
    weights: WeightsOpt = None,
    gaussian_head: GaussianHeadOpt = None,
    dino: DinoOpt = None,
    fusion: FusionOpt = None,
    device: DeviceOpt = "cpu",
    precision: PrecisionOpt = "fp32",
    lpips_weights: Annotated[
        Path | None,
        typer.Option(
            "--lpips-weights",
            metavar="PATH",
            help="Also LPIPS: a folder with torchvision's vgg16-*.pth and LPIPS v0.1 vgg.pth (or one file with both).",
        ),
    ] = None,
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Evaluate a reconstruction backend on a data set of posed images.

    Two context views per case (their relative pose estimated by the backend; more with
    --context-views), target views between them rendered from their true cameras; PSNR/SSIM
    (whole image and over the Splatt3R visibility mask), pose error and AUC, focal and depth
    error, time, next to two baselines (coloured point cloud, nearest context photo). Results are written after every
    case: a partial run keeps what it finished. LPIPS only with --lpips-weights (local VGG weights).

    [bold]Examples[/]

      macsplat eval --data scannetpp/ --split close,wide --out results/
      macsplat eval --data co3d_apple/ --intrinsics estimated --max-pairs 3
    """
    with command_context(ctx, verbose, quiet) as state:
        if jobs > 1:
            from .eval_jobs import eval_jobs

            def count_cases() -> int:  # as each shard will select them
                return len(_select(
                    data=data, layout=layout.value, scannetpp_split=scannetpp_split, scenes=scenes, cases_file=cases,
                    split=split, split_by=split_by.value, assignment=assignment.value, max_pairs=max_pairs,
                    max_targets=max_targets, seed=seed, quiet=state.quiet, context_views=context_views,
                    proto=_protocol(protocol, cases),
                )[1].cases)  # fmt: skip

            eval_jobs(jobs, out, shard, state.quiet, json_out, splatt3r_compatible, count_cases)
            return
        _eval(
            data=data, split=split, backend=backend, out=out, layout=layout.value, scannetpp_split=scannetpp_split,
            scenes=scenes, cases_file=cases, size=size, eval_size=eval_size, intrinsics=intrinsics.value,
            conf_threshold=conf_threshold,
            max_pairs=max_pairs, max_targets=max_targets, split_by=split_by.value,
            assignment=assignment.value, seed=seed, context_views=context_views,
            splatt3r_compatible=splatt3r_compatible, baselines=not no_baselines, json_out=json_out, quiet=state.quiet,
            lpips_weights=lpips_weights, shard=shard, protocol=protocol,
            engine=engine_config(
                backend, conf_threshold=conf_threshold, refine=parse_refine(refine), quality=quality, matcher=matcher,
                neural=neural_options(weights, gaussian_head, dino, fusion, device, precision),
            ),
        )  # fmt: skip


def _eval(
    *, data: Path, split: str, backend: str, out: Path, layout: str, scannetpp_split: str, scenes: str | None,
    cases_file: Path | None, size: int | None, eval_size: int | None, intrinsics: str, conf_threshold: float | None,
    max_pairs: int,
    max_targets: int, split_by: str, assignment: str, seed: int, splatt3r_compatible: bool, baselines: bool,
    json_out: bool, quiet: bool, engine: EngineConfig, lpips_weights: Path | None = None, context_views: int = 2,
    shard: str | None = None, protocol: str | None = None,
) -> None:  # fmt: skip
    import time

    from .._json import to_jsonable
    from ..errors import DatasetError
    from ..evaluation import EvalConfig, ReconstructSettings, ResultWriter, make_reconstructor
    from ..evaluation.contexts import check_context_views
    from ..evaluation.results import BASELINES
    from ..evaluation.shards import parse_shard, shard_cases, shard_record
    from ..evaluation.splits import parse_splits
    from ..evaluation.summary import summarize
    from ..lpips import load_lpips

    parse_splits(split)  # bad options fail before any work
    shard_at = parse_shard(shard) if shard is not None else None
    proto = _protocol(protocol, cases_file)
    check_context_views(context_views, backends=[engine.backend])
    ResultWriter.check(out)  # and outputs that cannot be written (a link, a device, a read-only folder)
    check_no_clobber(
        [(f"--out {out}:", out / name) for name in ResultWriter.FILES],
        [("--cases", cases_file), ("--lpips-weights", lpips_weights)],
    )
    lpips = load_lpips(lpips_weights) if lpips_weights is not None else None
    reconstructor = make_reconstructor(engine)
    from ..presets import resolved_refine_steps, working_size

    steps = resolved_refine_steps(engine.quality, engine.overrides)  # as configure resolves them (any backend)
    size = size if size is not None else working_size(engine.quality)
    dataset, sel = _select(
        data=data, layout=layout, scannetpp_split=scannetpp_split, scenes=scenes, cases_file=cases_file, split=split,
        split_by=split_by, assignment=assignment, max_pairs=max_pairs, max_targets=max_targets, seed=seed, quiet=quiet,
        context_views=context_views, proto=proto,
    )  # fmt: skip
    import tempfile

    with tempfile.TemporaryDirectory(prefix="macsplat-crop-") as crops:
        config = EvalConfig(
            settings=ReconstructSettings(size=size, intrinsics=intrinsics),  # type: ignore[arg-type]
            eval_size=eval_size,
            splatt3r_compatible=splatt3r_compatible,
            baselines=BASELINES if baselines else (),
            lpips=lpips,
        )
        extra = {
            "command": "macsplat eval",
            "split_modes": sel.modes,
            "candidates": sel.candidates,
            "options": {"split": split, "max_pairs": max_pairs, "max_targets": max_targets, "seed": seed,
                        "assignment": assignment, "split_by": split_by, "backend": backend,
                        "refine": steps, "conf_threshold": conf_threshold,
                        "context_views": context_views, "protocol": protocol},
        }  # fmt: skip
        if shard_at is not None:  # the run's cases and this shard's place in it, for eval merge
            extra["shard"] = shard_record(sel.cases, *shard_at)
            sel.cases = shard_cases(sel.cases, *shard_at)
        if proto is not None and proto.crop is not None:  # the protocol's frames: cropped copies of this shard's
            from ..evaluation.crop import crop_frames

            dataset = crop_frames(dataset, sel.cases, proto.crop, Path(crops))
        writer = ResultWriter(out, extra)
        writer.write_coverage(sel.coverage, {s.name: [f.name for f in s.frames] for s in dataset.scenes})
        if not quiet:
            _announce(sel.cases, dataset, context_views, reconstructor.name)
        t0 = time.perf_counter()
        run = run_with_progress(dataset, sel.cases, reconstructor, config, writer, quiet)
        rows = summarize(run)
        if not quiet:
            print_summary(run, rows, writer, splatt3r_compatible, time.perf_counter() - t0)
        if json_out:
            out_console.print_json(json.dumps({"summary": to_jsonable(rows), "results": str(writer.json_path)}))
        if run.errors:
            first = run.errors[0]
            raise DatasetError(
                f"{len(run.errors)} of {len(run.results)} case(s) could not be evaluated because of bad input "
                f"(first: {first.case.key}: {first.error}); the other cases' results are in {out}"
            )


def _select(
    *, data: Path, layout: str, scannetpp_split: str, scenes: str | None, cases_file: Path | None, split: str,
    split_by: str, assignment: str, max_pairs: int, max_targets: int, seed: int, quiet: bool, context_views: int,
    proto: Any,
) -> tuple[EvalDataset, CaseSelection]:  # fmt: skip
    """The data set (the protocol's ScanNet++ split, if any) and the run's cases (:func:`select_cases`)."""
    from ..evaluation.splits import parse_splits

    parse_splits(split)  # a bad --split fails before the data set is read
    dataset = load_data(data, layout, proto.scannetpp_split if proto is not None else scannetpp_split, scenes)
    return dataset, select_cases(
        dataset, cases_file=cases_file, split=split, split_by=split_by, assignment=assignment,
        max_pairs=max_pairs, max_targets=max_targets, seed=seed, quiet=quiet, context_views=context_views,
        every=proto.every_nth_row if proto else 1, exclude=proto.exclude_scenes if proto else (),
    )  # fmt: skip


def _announce(cases: list[Any], dataset: Any, context_views: int, backend: str) -> None:
    """What the run is about to do, on one line."""
    err_console.print(
        escape(
            f"{len(cases)} case(s) from {len(dataset.scenes)} scene(s) ({dataset.layout}), "
            f"{sum(len(c.targets) for c in cases)} target view(s)"
            + (f", {context_views} context views each" if context_views > 2 else "")
            + f"; backend {backend}"
        ),
        highlight=False,
    )


def _protocol(name: str | None, cases_file: Path | None) -> Any:
    """``--protocol``: the :class:`~macsplat_cli.evaluation.protocols.EvalProtocol`, its needs checked; None without."""
    from ..errors import InputError
    from ..evaluation.protocols import get_protocol

    if name is None:
        return None
    proto = get_protocol(name)
    if proto.needs_cases and cases_file is None:
        raise InputError(f"--protocol {proto.name} evaluates published test sets: give --cases, {proto.cases_hint}")
    return proto
