"""The library entry points of ``macsplat eval`` and ``macsplat bench``: one spec in, the run out.

:func:`run` evaluates one backend (:class:`EvalSpec`), :func:`benchmark` a grid of settings (:class:`BenchSpec`),
both on the cases :func:`select` draws from a data set (:class:`CaseSpec`). Everything is checked before any work
(bad options, outputs that cannot be written or would overwrite an input), in the order the commands have always
checked it. What a caller shows while a run goes (progress bars, notices) is a :class:`EvalProgress`; this module
draws nothing: the CLI maps its options onto a spec, passes its Rich progress, and prints the tables of the result.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from .._atomic import check_no_clobber
from ..engine import EngineConfig, NeuralOptions
from ..errors import DatasetError, InputError
from ..presets import DEFAULT_MATCHER, Matcher, Quality
from .bench import BENCH_FILES, METRICS, BenchRow, check_bench_outputs, grid, run_bench
from .contexts import check_context_views, extend_cases
from .protocol import check_context_sizes, evaluate
from .protocols import EvalProtocol, get_protocol
from .reconstructors import BACKENDS, IntrinsicsMode, Reconstructor, ReconstructSettings, make_reconstructor
from .result_files import ResultWriter
from .results import BASELINES, CaseResult, EvalConfig, EvalRun
from .shards import parse_shard, shard_cases, shard_record
from .splits import Assignment, CaseSelection, EvalCase, SplitConfig, SplitMode, load_cases, make_cases, parse_splits
from .summary import summarize

if TYPE_CHECKING:
    from ..datasets import EvalDataset
    from ..datasets.base import Layout

__all__ = [
    "BenchSpec",
    "CaseSpec",
    "EvalOutcome",
    "EvalProgress",
    "EvalSpec",
    "Silent",
    "benchmark",
    "run",
    "select",
]

OnCase = Callable[[int, EvalCase, "CaseResult | None"], None]
"""``(index, case, None)`` before a case, ``(index, case, result)`` after it (:func:`~.protocol.evaluate`)."""


class EvalProgress(Protocol):
    """What a caller shows while cases are drawn and run (the CLI draws Rich bars; :class:`Silent` nothing)."""

    def coverage(self) -> AbstractContextManager[Callable[[str, int, int], None] | None]:
        """Around the pairwise coverage of the scenes: yields ``(scene, done, total) -> None``, or None."""
        ...

    def notice(self, text: str) -> None:
        """A line the user should read (cases left out)."""
        ...

    def announce(self, text: str) -> None:
        """What the run is about to do, on one line."""
        ...

    def cases(self, total: int, label: str, folder: Path | None) -> AbstractContextManager[OnCase | None]:
        """Around the run of ``total`` cases (``label``: the bench setting, or ""; ``folder``: where the results
        go, None: nowhere): yields the :data:`OnCase` callback, or None."""
        ...


class Silent:
    """The :class:`EvalProgress` that shows nothing (a library caller's default)."""

    def coverage(self) -> AbstractContextManager[Callable[[str, int, int], None] | None]:
        return contextlib.nullcontext(None)

    def notice(self, text: str) -> None:
        pass

    def announce(self, text: str) -> None:
        pass

    def cases(self, total: int, label: str, folder: Path | None) -> AbstractContextManager[OnCase | None]:
        return contextlib.nullcontext(None)


@dataclass
class CaseSpec:
    """The data set and how its test cases are drawn (or read from a file).

    Args:
        data: the data set's folder.
        layout: its folder layout (:data:`~macsplat_cli.datasets.LAYOUTS`; ``auto`` detects it).
        scannetpp_split: ScanNet++: the split file to take the scenes from (a protocol's takes precedence).
        scenes: only these scenes (None: all).
        cases_file: explicit test cases (JSON), instead of drawing them.
        split: the splits, comma-separated (``close``, ``medium``, ``wide``, ``very-wide``), or ``all``.
        split_by: ``coverage`` (needs depth), ``angle``, or ``auto``.
        assignment: ``bin`` (each pair in its tightest split) or ``threshold`` (thresholds as lower bounds).
        max_pairs: context pairs per split and scene (0: all), drawn with ``seed``.
        max_targets: targets per pair (0: all).
        seed: seed of the pair and target draws.
        context_views: context photos per case (more than 2: the pair extended, :mod:`.contexts`).
        protocol: a paper's protocol (:mod:`.protocols`), or None.
    """

    data: Path
    layout: Layout = "auto"
    scannetpp_split: str = "nvs_sem_val"
    scenes: list[str] | None = None
    cases_file: Path | None = None
    split: str = "all"
    split_by: SplitMode = "auto"
    assignment: Assignment = "bin"
    max_pairs: int = 5
    max_targets: int = 3
    seed: int = 0
    context_views: int = 2
    protocol: str | None = None


@dataclass
class EvalSpec:
    """One backend measured on a data set (``macsplat eval``).

    Args:
        cases: the data set and its cases.
        engine: the backend's engine settings, resolved as ``macsplat reconstruct``'s.
        out: the results folder (``results.json``, ``results.csv``, ``cases.jsonl``, ...).
        eval_size: compare views at this long side (None: the working size, ``engine.overrides.size`` or the
            quality's).
        intrinsics: ``given`` (the true intrinsics go to the backend) or ``estimated``.
        splatt3r_compatible: Splatt3R's metric convention.
        baselines: also the point-cloud and copy baselines.
        lpips_weights: LPIPS-VGG weights (None: no LPIPS).
        shard: ``I/N``: only every N-th case from the I-th (then ``eval merge``); None: all.
    """

    cases: CaseSpec
    engine: EngineConfig = field(default_factory=EngineConfig)
    out: Path = Path("results")
    eval_size: int | None = None
    intrinsics: IntrinsicsMode = "given"
    splatt3r_compatible: bool = False
    baselines: bool = True
    lpips_weights: Path | None = None
    shard: str | None = None


@dataclass
class EvalOutcome:
    """A finished run: its results, their summary rows (:func:`~.summary.summarize`), where they were written,
    and how long the cases took."""

    run: EvalRun
    rows: list[dict[str, Any]]
    writer: ResultWriter
    seconds: float

    def check(self) -> None:
        """Raises :class:`~macsplat_cli.errors.DatasetError` when a case could not be evaluated (bad input)."""
        if self.run.errors:
            first = self.run.errors[0]
            raise DatasetError(
                f"{len(self.run.errors)} of {len(self.run.results)} case(s) could not be evaluated because of bad "
                f"input (first: {first.case.key}: {first.error}); the other cases' results are in {self.writer.folder}"
            )


@dataclass
class BenchSpec:
    """A grid of settings measured on the same cases (``macsplat bench``); every combination of the lists.

    Args:
        cases: the data set and its cases (no protocol).
        out: the bench folder (``bench.md``, ``bench.png``, ``bench.json``, ``runs/``).
        backends: backend names (:data:`~.reconstructors.BACKENDS`).
        sizes: working sizes.
        taus: matching thresholds τ (None: the default).
        steps: refinement steps (None: each quality's).
        qualities: presets.
        matchers: the classical backend's matchers.
        neural: the neural backend's files and device.
        metric: the quality axis (:data:`~.bench.METRICS`).
        eval_size: compare every setting's views at this long side (None: the largest size).
        intrinsics: ``given`` or ``estimated``.
        splatt3r_compatible: Splatt3R's metric convention.
    """

    cases: CaseSpec
    out: Path = Path("bench")
    backends: list[str] = field(default_factory=lambda: ["classical"])
    sizes: list[int] = field(default_factory=lambda: [384, 512])
    taus: list[float | None] = field(default_factory=lambda: [None])
    steps: list[int | None] = field(default_factory=lambda: [None])
    qualities: list[Quality] = field(default_factory=lambda: ["balanced"])
    matchers: list[Matcher] = field(default_factory=lambda: [DEFAULT_MATCHER])
    neural: NeuralOptions = field(default_factory=NeuralOptions)
    metric: str = "psnr"
    eval_size: int | None = None
    intrinsics: IntrinsicsMode = "given"
    splatt3r_compatible: bool = False


def protocol_of(spec: CaseSpec) -> EvalProtocol | None:
    """``spec.protocol``'s :class:`~.protocols.EvalProtocol`, its needs checked; None without one.

    Raises:
        InputError: an unknown protocol, or one that evaluates published test sets without ``cases_file``.
    """
    if spec.protocol is None:
        return None
    proto = get_protocol(spec.protocol)
    if proto.needs_cases and spec.cases_file is None:
        raise InputError(f"--protocol {proto.name} evaluates published test sets: give --cases, {proto.cases_hint}")
    return proto


def select(spec: CaseSpec, progress: EvalProgress | None = None) -> tuple[EvalDataset, CaseSelection]:
    """The data set (the protocol's ScanNet++ split, if any) and the run's cases: from the file, or drawn from the
    splits; with more than two context views, each case's pair extended (:mod:`.contexts`).

    Raises:
        DatasetError: a bad data set or cases file; no case left (the message says which option to change).
        InputError: a bad split or protocol.
    """
    return _select(spec, protocol_of(spec), progress or Silent())


def _select(
    spec: CaseSpec, proto: EvalProtocol | None, progress: EvalProgress
) -> tuple[EvalDataset, CaseSelection]:  # fmt: skip
    """:func:`select` with the protocol already checked."""
    from ..datasets import load_dataset

    splits = parse_splits(spec.split)  # a bad --split fails before the data set is read
    dataset = load_dataset(
        spec.data, spec.layout, scannetpp_split=proto.scannetpp_split if proto else spec.scannetpp_split,
        scenes=spec.scenes,
    )  # fmt: skip
    n = spec.context_views
    if spec.cases_file is not None:
        sel = load_cases(
            spec.cases_file, dataset, every=proto.every_nth_row if proto else 1,
            exclude=proto.exclude_scenes if proto else (),
        )  # fmt: skip
        if spec.split.strip().lower() != "all":
            sel.cases = [c for c in sel.cases if c.split in splits]
        sel.cases, left = extend_cases(dataset, sel.cases, n)
        check_context_sizes(dataset, sel.cases)
    else:
        check_context_sizes(dataset)  # any frame may become a context view: before the O(N²) coverage
        cfg = SplitConfig(
            splits=splits, mode=spec.split_by, assignment=spec.assignment, max_pairs=spec.max_pairs or None,
            max_targets=spec.max_targets or None, seed=spec.seed,
        )  # fmt: skip
        with progress.coverage() as on_coverage:
            sel = make_cases(dataset, cfg, on_coverage=on_coverage)
        sel.cases, left = extend_cases(dataset, sel.cases, n, cfg.angle_slack_deg)
    if left:
        progress.notice(
            f"{len(left)} case(s) left out (first: {left[0].key}): too few frames besides their targets for "
            f"{n} context views"
        )
    if not sel.cases and left:
        raise DatasetError(
            f"{dataset.root}: no test case can have {n} context views (the scenes have too few frames besides the "
            "targets); try a smaller --context-views"
        )
    if not sel.cases:
        raise DatasetError(
            f"{dataset.root}: no test case for split {spec.split!r} (a pair needs a target, and an overlap or angle "
            "in the split's range); try --split all, --assignment threshold, or --cases FILE"
        )
    return dataset, sel


def run_cases(
    dataset: EvalDataset, cases: Sequence[EvalCase], reconstructor: Reconstructor, config: EvalConfig,
    writer: ResultWriter | None, progress: EvalProgress, label: str = "",
) -> EvalRun:  # fmt: skip
    """:func:`~.protocol.evaluate` inside ``progress.cases`` (partial results stay written on Ctrl-C)."""
    folder = writer.folder if writer is not None else None
    with progress.cases(len(cases), label, folder) as on_case:
        return evaluate(dataset, cases, reconstructor, config, writer=writer, on_case=on_case)


def _check_eval(spec: EvalSpec) -> EvalProtocol | None:
    """Everything about ``spec`` that can be checked before the models and the data set load; its protocol."""
    parse_splits(spec.cases.split)  # bad options fail before any work
    if spec.shard is not None:
        parse_shard(spec.shard)
    proto = protocol_of(spec.cases)
    check_context_views(spec.cases.context_views, backends=[spec.engine.backend])
    ResultWriter.check(spec.out)  # and outputs that cannot be written (a link, a device, a read-only folder)
    check_no_clobber(
        [(f"--out {spec.out}:", spec.out / name) for name in ResultWriter.FILES],
        [("--cases", spec.cases.cases_file), ("--lpips-weights", spec.lpips_weights)],
    )
    return proto


def run(spec: EvalSpec, progress: EvalProgress | None = None) -> EvalOutcome:
    """Evaluate ``spec.engine``'s backend on the cases of ``spec.cases``, writing the results as it goes.

    Returns:
        The run; :meth:`EvalOutcome.check` raises if a case had bad input (the caller shows the tables first).

    Raises:
        InputError, DatasetError, OutputPathError: bad options, data or outputs, before any case.
    """
    from ..lpips import load_lpips
    from ..presets import resolved_refine_steps, resolved_size
    from .crop import crop_frames

    progress = progress or Silent()
    proto = _check_eval(spec)
    lpips = load_lpips(spec.lpips_weights) if spec.lpips_weights is not None else None
    engine = spec.engine
    reconstructor = make_reconstructor(engine)
    steps = resolved_refine_steps(engine.quality, engine.overrides)  # as configure resolves them (any backend)
    size = resolved_size(engine.quality, engine.overrides)
    dataset, sel = _select(spec.cases, proto, progress)
    c = spec.cases
    with tempfile.TemporaryDirectory(prefix="macsplat-crop-") as crops:
        config = EvalConfig(
            settings=ReconstructSettings(size=size, intrinsics=spec.intrinsics), eval_size=spec.eval_size,
            splatt3r_compatible=spec.splatt3r_compatible, baselines=BASELINES if spec.baselines else (), lpips=lpips,
        )  # fmt: skip
        extra: dict[str, Any] = {
            "command": "macsplat eval",
            "split_modes": sel.modes,
            "candidates": sel.candidates,
            "options": {"split": c.split, "max_pairs": c.max_pairs, "max_targets": c.max_targets, "seed": c.seed,
                        "assignment": c.assignment, "split_by": c.split_by, "backend": engine.backend,
                        "refine": steps, "conf_threshold": engine.overrides.conf_threshold,
                        "context_views": c.context_views, "protocol": c.protocol},
        }  # fmt: skip
        if spec.shard is not None:  # the run's cases and this shard's place in it, for eval merge
            at = parse_shard(spec.shard)
            extra["shard"] = shard_record(sel.cases, *at)
            sel.cases = shard_cases(sel.cases, *at)
        if proto is not None and proto.crop is not None:  # the protocol's frames: cropped copies of this shard's
            dataset = crop_frames(dataset, sel.cases, proto.crop, Path(crops))
        writer = ResultWriter(spec.out, extra)
        writer.write_coverage(sel.coverage, {s.name: [f.name for f in s.frames] for s in dataset.scenes})
        progress.announce(
            f"{len(sel.cases)} case(s) from {len(dataset.scenes)} scene(s) ({dataset.layout}), "
            f"{sum(len(k.targets) for k in sel.cases)} target view(s)"
            + (f", {c.context_views} context views each" if c.context_views > 2 else "")
            + f"; backend {reconstructor.name}"
        )
        t0 = time.perf_counter()
        result = run_cases(dataset, sel.cases, reconstructor, config, writer, progress)
        return EvalOutcome(result, summarize(result), writer, time.perf_counter() - t0)


def _check_bench(spec: BenchSpec) -> None:
    """The grid's values, each checked once, before any work."""
    from ..presets import check_quality

    if spec.metric not in METRICS:
        raise InputError(f"--metric {spec.metric!r}: use one of {', '.join(METRICS)}")
    unknown = [b for b in spec.backends if b not in BACKENDS]
    if unknown:
        raise InputError(f"--backend {unknown[0]!r}: available: {', '.join(sorted(BACKENDS))}")
    if any(s < 64 for s in spec.sizes) or any(t is not None and t < 0 for t in spec.taus):
        raise InputError("--size must be ≥ 64 and --conf-threshold ≥ 0")
    check_context_views(spec.cases.context_views, backends=spec.backends)
    for q in spec.qualities:
        check_quality(q)
    for m in spec.matchers:
        EngineConfig(matcher=m).validate()
    if spec.neural.given and "neural" not in spec.backends:
        raise InputError(f"{', '.join(spec.neural.given)} only apply to --backend neural")
    if "neural" in spec.backends:  # usage errors (no weights, --dino without --fusion, ...) before any work
        EngineConfig(backend="neural", neural=spec.neural).validate()


def benchmark(spec: BenchSpec, progress: EvalProgress | None = None) -> list[BenchRow]:
    """Evaluate every setting of ``spec``'s grid on the same cases; write ``bench.md``, ``bench.png``,
    ``bench.json`` and each setting's results under ``runs/`` (:func:`~.bench.run_bench`).

    Returns:
        The rows, Pareto front marked.

    Raises:
        InputError, DatasetError, OutputPathError: bad options, data or outputs, before any setting runs.
    """
    progress = progress or Silent()
    _check_bench(spec)
    settings = grid(spec.backends, spec.sizes, spec.taus, spec.steps, spec.qualities, spec.matchers)
    check_bench_outputs(spec.out, settings)  # every file of the bench and of each setting's run, before any work
    check_no_clobber(
        [(f"--out {spec.out}:", spec.out / name) for name in BENCH_FILES]
        + [(f"--out {spec.out}:", spec.out / "runs" / s.slug / name) for s in settings for name in ResultWriter.FILES],
        [("--cases", spec.cases.cases_file)],
    )
    dataset, sel = _select(spec.cases, None, progress)  # a bench has no protocol
    n = spec.cases.context_views
    each = f", {n} context views each" if n > 2 else ""
    progress.announce(
        f"{len(settings)} setting(s) × {len(sel.cases)} case(s) from {len(dataset.scenes)} scene(s){each}"
    )

    def run_fn(
        dataset: EvalDataset, cases: Sequence[EvalCase], recon: Reconstructor, cfg: EvalConfig,
        writer: ResultWriter | None, index: int,
    ) -> EvalRun:  # fmt: skip
        label = f"[{index + 1}/{len(settings)}] {settings[index].slug} "
        return run_cases(dataset, list(cases), recon, cfg, writer, progress, label=label)

    return run_bench(
        dataset, sel.cases, settings, metric=spec.metric, intrinsics=spec.intrinsics, eval_size=spec.eval_size,
        splatt3r_compatible=spec.splatt3r_compatible, out_dir=spec.out, run_fn=run_fn,
        base=EngineConfig(neural=spec.neural),
    )  # fmt: skip
