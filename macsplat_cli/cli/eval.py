"""``macsplat eval``: measure a backend on a data set of posed images (splits, metrics, baselines)."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ..presets import DEFAULT_MATCHER
from ._app import app
from ._common import QuietOpt, VerboseOpt, command_context, err_console, escape, out_console
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
    choice,
    engine_config,
    neural_options,
    parse_refine,
)

if TYPE_CHECKING:
    from rich.progress import TaskID

    from ..datasets import Layout
    from ..evaluation import CaseResult, CaseSpec, EvalCase
    from ..evaluation.commands import OnCase
    from ..evaluation.reconstructors import IntrinsicsMode
    from ..evaluation.splits import Assignment, SplitMode

logger = logging.getLogger("macsplat_cli.cli.eval")


LAYOUTS: tuple[Layout, ...] = ("auto", "generic", "scannetpp", "co3d-json", "icl-nuim", "nyu-rgbd")
"""``--layout``: :data:`macsplat_cli.datasets.LAYOUTS`, spelled here so that ``--help`` reads no library module."""
INTRINSICS: tuple[IntrinsicsMode, ...] = ("given", "estimated")
SPLIT_MODES: tuple[SplitMode, ...] = ("auto", "coverage", "angle")
ASSIGNMENTS: tuple[Assignment, ...] = ("bin", "threshold")


DataOpt = Annotated[
    Path,
    typer.Option(
        "--data", metavar="DIR", help="Data set folder (generic, ScanNet++, CO3D sample, ICL-NUIM/NYU RGB-D)."
    ),
]


SplitOpt = Annotated[str, typer.Option("--split", help="close, medium, wide, very-wide (comma-separated), or all.")]
LayoutOpt = Annotated[str, typer.Option("--layout", metavar="|".join(LAYOUTS), help="Folder layout (auto: detect it).")]
ScannetSplitOpt = Annotated[
    str, typer.Option("--scannetpp-split", help="ScanNet++: the split file to take the scenes from.")
]
ScenesOpt = Annotated[str | None, typer.Option("--scenes", help="Only these scenes (comma-separated).")]
CasesOpt = Annotated[
    Path | None,
    typer.Option("--cases", metavar="FILE", help="Explicit test cases (JSON; also Splatt3R's test_set_*.json)."),
]
IntrinsicsOpt = Annotated[
    str,
    typer.Option(
        "--intrinsics",
        metavar="|".join(INTRINSICS),
        help="given: pass the true intrinsics; estimated: the backend finds them.",
    ),
]
MaxPairsOpt = Annotated[
    int, typer.Option("--max-pairs", min=0, help="Context pairs per split and scene (0 = all), drawn with --seed.")
]
MaxTargetsOpt = Annotated[int, typer.Option("--max-targets", min=0, help="Targets per pair (0 = all).")]
SplitByOpt = Annotated[
    str,
    typer.Option("--split-by", metavar="|".join(SPLIT_MODES), help="Coverage (needs depth), view angle, or auto."),
]
AssignmentOpt = Annotated[
    str,
    typer.Option(
        "--assignment",
        metavar="|".join(ASSIGNMENTS),
        help="bin: each pair in its tightest split; threshold: thresholds as lower bounds.",
    ),
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


class RichProgress:
    """The evaluation's :class:`~macsplat_cli.evaluation.EvalProgress` on stderr: transient Rich bars for the
    coverage and the cases, a yellow notice, the run's one-line announcement; nothing but errors when ``quiet``."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet

    @contextlib.contextmanager
    def coverage(self) -> Iterator[Callable[[str, int, int], None]]:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

        progress = Progress(
            TextColumn("coverage {task.description}", markup=False),  # scene names are not markup
            BarColumn(), MofNCompleteColumn(), console=err_console, disable=self.quiet, transient=True,
        )  # fmt: skip
        tasks: dict[str, TaskID] = {}

        def on_coverage(scene: str, done: int, total: int) -> None:
            if scene not in tasks:
                tasks[scene] = progress.add_task(scene, total=total)
            progress.update(tasks[scene], completed=done)

        with progress:
            yield on_coverage

    def notice(self, text: str) -> None:
        if not self.quiet:
            err_console.print(escape(text), style="yellow", highlight=False)

    def announce(self, text: str) -> None:
        if not self.quiet:
            err_console.print(escape(text), highlight=False)

    @contextlib.contextmanager
    def cases(self, total: int, label: str, folder: Path | None) -> Iterator[OnCase]:
        """A bar over the cases with the last one's pose error; on Ctrl-C, where the finished cases are."""
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        progress = Progress(
            TextColumn(label + "{task.description:<32}", markup=False),  # case keys are not markup
            BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("{task.fields[last]}", markup=False),
            console=err_console, disable=self.quiet, transient=True,
        )  # fmt: skip
        task = progress.add_task("", total=total, last="")

        def on_case(i: int, case: EvalCase, res: CaseResult | None) -> None:
            if res is None:
                progress.update(task, description=case.key)
                return
            last = {"ok": f"pose err {res.pose_error_deg:.1f}°", "failed": "failed", "error": "input error"}[res.status]
            progress.update(task, completed=i + 1, last=last)

        try:
            with progress:
                yield on_case
        except KeyboardInterrupt:
            if folder is not None:
                err_console.print(
                    f"interrupted: the cases finished so far are in {escape(str(folder))}", style="yellow"
                )
            raise


def case_spec(
    data: Path, *, layout: str, scannetpp_split: str, scenes: str | None, cases: Path | None, split: str,
    split_by: str, assignment: str, max_pairs: int, max_targets: int, seed: int, context_views: int,
    protocol: str | None = None,
) -> CaseSpec:  # fmt: skip
    """The options that choose the cases (``eval`` and ``bench`` share them), as the library takes them."""
    from ..evaluation import CaseSpec

    names = [s.strip() for s in scenes.split(",") if s.strip()] if scenes else None
    return CaseSpec(
        data=data, layout=choice("--layout", layout, LAYOUTS, sep=", "), scannetpp_split=scannetpp_split,
        scenes=names, cases_file=cases, split=split, split_by=choice("--split-by", split_by, SPLIT_MODES, sep=", "),
        assignment=choice("--assignment", assignment, ASSIGNMENTS), max_pairs=max_pairs, max_targets=max_targets,
        seed=seed, context_views=context_views, protocol=protocol,
    )  # fmt: skip


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
    layout: LayoutOpt = "auto",
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
    intrinsics: IntrinsicsOpt = "given",
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
    split_by: SplitByOpt = "auto",
    assignment: AssignmentOpt = "bin",
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
        from .. import evaluation
        from .._json import to_jsonable

        cases_spec = case_spec(
            data, layout=layout, scannetpp_split=scannetpp_split, scenes=scenes, cases=cases, split=split,
            split_by=split_by, assignment=assignment, max_pairs=max_pairs, max_targets=max_targets, seed=seed,
            context_views=context_views, protocol=protocol,
        )  # fmt: skip
        progress = RichProgress(state.quiet)
        if jobs > 1:
            from .eval_jobs import eval_jobs

            eval_jobs(jobs, out, shard, state.quiet, json_out, splatt3r_compatible,  # the cases, as each shard's
                      lambda: len(evaluation.select(cases_spec, progress)[1].cases))  # fmt: skip
            return
        spec = evaluation.EvalSpec(
            cases=cases_spec, out=out, eval_size=eval_size, intrinsics=choice("--intrinsics", intrinsics,
            INTRINSICS), splatt3r_compatible=splatt3r_compatible, baselines=not no_baselines,
            lpips_weights=lpips_weights, shard=shard,
            engine=engine_config(
                backend, conf_threshold=conf_threshold, refine=parse_refine(refine), size=size, quality=quality,
                matcher=matcher, neural=neural_options(weights, gaussian_head, dino, fusion, device, precision),
            ),
        )  # fmt: skip
        outcome = evaluation.run(spec, progress)
        if not state.quiet:
            print_summary(outcome.run, outcome.rows, outcome.writer, splatt3r_compatible, outcome.seconds)
        if json_out:
            summary = {"summary": to_jsonable(outcome.rows), "results": str(outcome.writer.json_path)}
            out_console.print_json(json.dumps(summary))
        outcome.check()
