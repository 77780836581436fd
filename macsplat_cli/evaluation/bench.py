"""``macsplat bench``: the evaluation over a grid of settings, and its time-vs-quality Pareto front.

Every setting (backend × working size × matching confidence threshold × refinement
steps; further axes are added to :class:`BenchSetting` and :func:`grid`) evaluates the
same cases (:func:`~.protocol.evaluate`, without baselines), with as many context views as
the cases have (``--context-views``: :mod:`.contexts`).

**Fair comparison.** Every setting's views are rendered and compared at one resolution
(``eval_size``, by default the largest working size of the grid): a smaller working size
must not score higher because its images are smaller and smoother. A setting that fails on
the hard cases would otherwise average its image metrics over the easy ones only and look
best. So a row's image metrics (PSNR,
SSIM, masked), its median pose errors and its time per pair are measured on the
**common** cases: those that every setting of the bench reconstructed (``common``
targets in the table). Failures are counted in ``failed`` and in the pose AUC (180° each,
over all cases). The Pareto front holds the settings that no other setting matches or
beats on all three of time per pair, the chosen quality metric (:data:`METRICS`:
higher-is-better metrics are maximised, errors minimised) and the number of failures,
and beats on one.

:func:`bench_markdown` writes the table, :func:`bench_plot` a PNG scatter plot of time
against the metric (OpenCV drawing; no plotting library).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from .._atomic import atomic_write_bytes, atomic_write_text, check_folder, check_writable
from .._json import to_jsonable
from ..datasets import EvalDataset
from ..engine import EngineConfig, Models, NeuralOptions, load_models
from ..errors import InputError, OutputPathError
from ..pipeline.refine import RefineConfig
from ..presets import BACKENDS as ENGINE
from ..presets import DEFAULT_MATCHER, Quality
from ..presets import refine_steps as preset_refine_steps
from .protocol import evaluate
from .reconstructors import BACKENDS, IntrinsicsMode, Reconstructor, ReconstructSettings, make_reconstructor
from .result_files import ResultWriter
from .results import EvalConfig, EvalRun
from .splits import EvalCase
from .summary import format_cell, summarize

__all__ = [
    "METRICS",
    "BenchRow",
    "BenchSetting",
    "bench_json",
    "bench_markdown",
    "bench_plot",
    "bench_rows",
    "grid",
    "mark_pareto",
    "pareto_front",
    "run_bench",
    "setting_config",
    "write_bench",
]

METRICS: dict[str, bool] = {
    "psnr": True,
    "psnr_masked": True,
    "ssim": True,
    "ssim_masked": True,
    "auc@5": True,
    "auc@10": True,
    "auc@20": True,
    "rotation_error_deg": False,
    "translation_error_deg": False,
    "depth_absrel": False,
}
"""Quality metrics a bench can optimise → higher is better."""


@dataclass(frozen=True)
class BenchSetting:
    """One point of the grid."""

    backend: str = "classical"
    size: int = 512
    conf_threshold: float | None = None
    refine_steps: int = 0
    quality: str = "balanced"
    matcher: str = DEFAULT_MATCHER

    @property
    def label(self) -> str:
        tau = "default" if self.conf_threshold is None else f"{self.conf_threshold:g}"
        label = f"{self.backend} size={self.size} tau={tau} refine={self.refine_steps} quality={self.quality}"
        return label if self.matcher == DEFAULT_MATCHER else f"{label} matcher={self.matcher}"

    @property
    def slug(self) -> str:
        tau = "d" if self.conf_threshold is None else f"{self.conf_threshold:g}"
        slug = f"{self.backend}_s{self.size}_t{tau}_r{self.refine_steps}_q{self.quality}"
        return slug if self.matcher == DEFAULT_MATCHER else f"{slug}_m{self.matcher}"


@dataclass
class BenchRow:
    """A setting and what it measured (``summary``: the run's ``all``-splits row)."""

    setting: BenchSetting
    summary: dict[str, Any]
    pareto: bool = False

    def value(self, key: str) -> float:
        v = self.summary.get(key)
        return math.nan if v is None else float(v)


def grid(
    backends: Sequence[str] = ("classical",),
    sizes: Sequence[int] = (512,),
    conf_thresholds: Sequence[float | None] = (None,),
    refine_steps: Sequence[int | None] = (None,),
    qualities: Sequence[str] = ("balanced",),
    matchers: Sequence[str] = (DEFAULT_MATCHER,),
) -> list[BenchSetting]:
    """Every combination of the axes, in order; a refinement of None is the quality's
    (:func:`~macsplat_cli.presets.refine_steps`, as ``reconstruct`` without ``--refine``); the neural backend matches
    its own (its settings take the default matcher once, whatever ``matchers`` holds)."""
    out: list[BenchSetting] = []
    for b, s, c, r, q, m in itertools.product(backends, sizes, conf_thresholds, refine_steps, qualities, matchers):
        steps = int(r) if r is not None else preset_refine_steps(cast(Quality, q))
        setting = BenchSetting(b, int(s), c, steps, q, DEFAULT_MATCHER if b == "neural" else m)
        if setting not in out:
            out.append(setting)
    return out


def setting_config(base: EngineConfig, setting: BenchSetting) -> EngineConfig:
    """The engine settings of one point of the grid: ``base`` (neural files and device, refinement scale) with the
    setting's backend, quality, matcher, τ and refinement steps (the working size comes per case)."""
    return base.replace(
        backend=setting.backend,
        quality=setting.quality,
        matcher=setting.matcher,
        overrides=dataclasses.replace(
            base.overrides, conf_threshold=setting.conf_threshold, refine=setting.refine_steps
        ),
        neural=base.neural if setting.backend == "neural" else NeuralOptions(),
    )


def pareto_front(
    points: Sequence[tuple[float, float]], higher_is_better: bool, failures: Sequence[int] | None = None
) -> list[int]:
    """Indices of the non-dominated points: time minimised, quality per ``higher_is_better``, failures minimised.

    A point with a NaN time or quality is never on the front.
    """
    sign = 1.0 if higher_is_better else -1.0
    fails = list(failures) if failures is not None else [0] * len(points)
    keys = [(t, -sign * q, f) for (t, q), f in zip(points, fails)]  # all three minimised
    finite = [math.isfinite(k[0]) and math.isfinite(k[1]) for k in keys]
    front = []
    for i, a in enumerate(keys):
        if not finite[i]:
            continue
        dominated = any(
            finite[j] and all(bj <= ai for bj, ai in zip(b, a)) and any(bj < ai for bj, ai in zip(b, a))
            for j, b in enumerate(keys)
            if j != i
        )
        if not dominated:
            front.append(i)
    return front


RunFn = Callable[[EvalDataset, Sequence[EvalCase], Reconstructor, EvalConfig, "ResultWriter | None", int], EvalRun]


def _default_run(
    dataset: EvalDataset,
    cases: Sequence[EvalCase],
    recon: Reconstructor,
    cfg: EvalConfig,
    writer: ResultWriter | None,
    index: int,
) -> EvalRun:
    return evaluate(dataset, cases, recon, cfg, writer=writer)


def _common_summary(run: EvalRun, common: set[str]) -> dict[str, Any]:
    """Image metrics, median pose errors and mean time over the cases in ``common``."""
    ok = [r for r in run.results if r.case.key in common and r.status == "ok"]
    per_target = [t.metrics[run.method] for r in ok for t in r.targets if run.method in t.metrics]

    def mean(values: list[float]) -> float:
        v = [x for x in values if x is not None and math.isfinite(x)]
        return float(np.mean(v)) if v else math.nan

    def median(values: list[float]) -> float:
        v = [x for x in values if math.isfinite(x)]
        return float(np.median(v)) if v else math.nan

    out: dict[str, Any] = {"common_cases": len(ok), "common_targets": len(per_target)}
    for key in ("psnr", "ssim", "psnr_masked", "ssim_masked"):
        out[key] = mean([m.get(key, math.nan) for m in per_target])
    out["rotation_error_deg"] = median([r.rotation_error_deg for r in ok])
    out["translation_error_deg"] = median([r.translation_error_deg for r in ok])
    out["time_s"] = mean([r.time_s for r in ok])
    return out


def bench_rows(settings: Sequence[BenchSetting], runs: Sequence[EvalRun], metric: str) -> list[BenchRow]:
    """One row per finished setting: the run's all-splits summary with the common-case measures, Pareto marked."""
    ok_sets = [{r.case.key for r in run.results if r.status == "ok"} for run in runs]
    common = set.intersection(*ok_sets) if ok_sets else set()
    rows = []
    for s, run in zip(settings, runs):
        summary = summarize(run)
        row = dict(next((r for r in summary if r["split"] == "all"), summary[0] if summary else {}))
        row["time_s_all_cases"] = row.get("time_s", math.nan)
        row.update(_common_summary(run, common))
        rows.append(BenchRow(s, row))
    return mark_pareto(rows, metric)


def mark_pareto(rows: Sequence[BenchRow], metric: str) -> list[BenchRow]:
    """The rows with ``pareto`` set (time per pair, ``metric``, failures)."""
    out = [BenchRow(r.setting, r.summary) for r in rows]
    points = [(r.value("time_s"), r.value(metric)) for r in out]
    fails = [int(r.summary.get("failed", 0) or 0) for r in out]
    for i in pareto_front(points, METRICS[metric], fails):
        out[i].pareto = True
    return out


BENCH_FILES = ("bench.md", "bench.json", "bench.png")
"""The files :func:`write_bench` writes into the output folder."""


def check_bench_outputs(out_dir: Path, settings: Sequence[BenchSetting]) -> None:
    """Before any work: every file a bench writes can be written, and ``runs/`` and its setting folders are
    real folders (no link to carry the results elsewhere; :func:`~.._atomic.check_folder`).

    Raises:
        OutputPathError: naming the file or folder.
    """
    out_dir = Path(out_dir)
    for name in BENCH_FILES:
        check_writable(out_dir / name)
    check_folder(out_dir / "runs")
    for s in settings:
        check_folder(out_dir / "runs" / s.slug)
        ResultWriter.check(out_dir / "runs" / s.slug)


def run_bench(
    dataset: EvalDataset,
    cases: Sequence[EvalCase],
    settings: Sequence[BenchSetting],
    *,
    metric: str = "psnr",
    intrinsics: IntrinsicsMode = "given",
    eval_size: int | None = None,
    splatt3r_compatible: bool = False,
    out_dir: Path | None = None,
    run_fn: RunFn | None = None,
    on_row: Callable[[list[BenchRow]], None] | None = None,
    base: EngineConfig | None = None,
) -> list[BenchRow]:
    """Evaluate every setting on the same cases and mark the Pareto front (module docstring).

    Args:
        dataset: the data set.
        cases: the cases (the same for every setting).
        settings: the grid.
        metric: the quality axis (a key of :data:`METRICS`).
        intrinsics: ``"given"`` or ``"estimated"``.
        eval_size: resolution (long side) at which every setting's views are compared
            (default: the largest working size of the grid).
        splatt3r_compatible: image metrics in Splatt3R's convention.
        out_dir: if given, each setting's results go to ``out_dir/runs/<slug>/`` and the
            bench files (:func:`write_bench`) to ``out_dir`` after every setting.
        run_fn: runs one setting's evaluation ``(dataset, cases, reconstructor, config,
            writer, setting index)`` (default :func:`~.protocol.evaluate`; the CLI adds progress).
        on_row: called with the rows so far after every setting.
        base: the engine settings the grid varies (neural files and device, refinement scale); each
            setting replaces its backend, τ and refinement steps. The models of each backend load once.

    Raises:
        InputError: unknown metric or backend.
        OutputPathError: an output under ``out_dir`` cannot be written (:func:`check_bench_outputs`),
            before any work.
    """
    if metric not in METRICS:
        raise InputError(f"unknown bench metric {metric!r}; use one of {', '.join(METRICS)}")
    for s in settings:
        if s.backend not in BACKENDS:  # unknown backends fail before any work
            raise InputError(f"unknown backend {s.backend!r}; available: {', '.join(sorted(BACKENDS))}")
    if out_dir is not None:
        check_bench_outputs(out_dir, settings)
    run = run_fn or _default_run
    eval_size = eval_size or max((s.size for s in settings), default=None)
    runs: list[EvalRun] = []
    rows: list[BenchRow] = []
    base = base or EngineConfig()
    models: dict[str, Models] = {}
    for i, s in enumerate(settings):
        config = setting_config(base, s)
        if s.backend not in models:  # the networks load once per backend
            models[s.backend] = load_models(config.replace(refine=RefineConfig())) if s.backend in ENGINE else Models()
        recon = make_reconstructor(config, models[s.backend])
        cfg = EvalConfig(
            settings=ReconstructSettings(size=s.size, intrinsics=intrinsics),
            eval_size=eval_size,
            splatt3r_compatible=splatt3r_compatible,
            baselines=(),
        )
        writer = None
        if out_dir is not None:  # checked again: runs/ might have become a link since check_bench_outputs
            check_folder(out_dir / "runs")
            writer = ResultWriter(check_folder(out_dir / "runs" / s.slug), {"setting": asdict(s)})
        runs.append(run(dataset, cases, recon, cfg, writer, i))
        rows = bench_rows(settings[: i + 1], runs, metric)
        if out_dir is not None:
            n_views = max((len(c.context) for c in cases), default=2)
            each = f", {n_views} context views each" if n_views > 2 else ""
            write_bench(out_dir, rows, metric, title=f"macsplat bench: {dataset.root} ({len(cases)} cases{each})")
        if on_row is not None:
            on_row(rows)
    return rows


def write_bench(out_dir: Path, rows: Sequence[BenchRow], metric: str, *, title: str = "") -> list[Path]:
    """Write ``bench.md``, ``bench.json`` and ``bench.png`` into ``out_dir`` (atomically)."""
    out_dir = Path(out_dir)
    md = (f"# {title}\n\n" if title else "") + bench_markdown(rows, metric)
    paths = [
        atomic_write_text(out_dir / "bench.md", md),
        atomic_write_text(out_dir / "bench.json", json.dumps(bench_json(rows, metric), indent=1) + "\n"),
        bench_plot(rows, metric, out_dir / "bench.png", title=title),
    ]
    return paths


BENCH_COLUMNS = (
    ("common_targets", "common targets", 0),
    ("time_s", "time s", 2),
    ("psnr", "PSNR", 2),
    ("ssim", "SSIM", 3),
    ("psnr_masked", "masked PSNR", 2),
    ("rotation_error_deg", "rot err °", 2),
    ("translation_error_deg", "t err °", 2),
    ("auc@10", "AUC@10", 3),
    ("depth_absrel", "AbsRel", 3),
    ("time_s_all_cases", "time s (all)", 2),
)


def bench_markdown(rows: Sequence[BenchRow], metric: str) -> str:
    """The grid as a Markdown table (Pareto-front settings in bold), then the front in time order."""
    columns: tuple[tuple[str, str, int], ...] = BENCH_COLUMNS
    n_views = max((int(r.summary.get("context_views") or 2) for r in rows), default=2)
    if n_views > 2:  # more than two contexts: how many of them were registered, on average
        columns = (*columns, ("registered", f"registered / {n_views}", 2))
    head = ["backend", "size", "τ", "refine", "quality", "matcher", *(c[1] for c in columns), "failed", "Pareto"]
    lines = ["| " + " | ".join(head) + " |", "|---|---:|---:|---:|---|---|" + "---:|" * len(columns) + "---:|:---:|"]
    for r in rows:
        s = r.setting
        cells = [
            s.backend,
            str(s.size),
            format_cell(s.conf_threshold, 3) if s.conf_threshold else "default",
            str(s.refine_steps),
            s.quality,
            s.matcher,
        ]
        cells += [format_cell(r.summary.get(k), d) for k, _, d in columns]
        cells += [f"{r.summary.get('failed', 0)}/{r.summary.get('cases', 0)}", "✓" if r.pareto else ""]
        if r.pareto:
            cells = [f"**{c}**" if c else c for c in cells]
        lines.append("| " + " | ".join(cells) + " |")
    direction = "higher" if METRICS[metric] else "lower"
    front = sorted((r for r in rows if r.pareto), key=lambda r: r.value("time_s"))
    lines += [
        "",
        "Image metrics, pose errors and time s: on the cases every setting reconstructed (common targets); "
        "AUC@10 and time s (all): over all cases, a failure counting as 180°.",
        "",
        f"Pareto front (time vs {metric}, {direction} is better, vs failures), fastest first:",
        "",
    ]
    cell = format_cell
    lines += [f"1. {r.setting.label}: {cell(r.value('time_s'))} s, {metric} {cell(r.value(metric), 3)}" for r in front]
    return "\n".join(lines) + "\n"


def bench_plot(rows: Sequence[BenchRow], metric: str, path: str | Path, *, title: str = "") -> Path:
    """A PNG scatter plot of time per pair (x) against ``metric`` (y), the Pareto front joined in red."""
    W, H, L, R, T, B = 900, 560, 80, 30, 50, 80
    img = np.full((H, W, 3), 255, np.uint8)
    pts = [(r.value("time_s"), r.value(metric)) for r in rows]
    ok = [(i, p) for i, p in enumerate(pts) if math.isfinite(p[0]) and math.isfinite(p[1])]
    font = cv2.FONT_HERSHEY_SIMPLEX
    grey, black, red, blue = (200, 200, 200), (0, 0, 0), (40, 40, 220), (200, 110, 30)
    grey_text = (90, 90, 90)
    cv2.putText(img, title or f"time per pair vs {metric}", (L, 30), font, 0.6, black, 1, cv2.LINE_AA)
    if ok:
        xs = np.array([p[0] for _, p in ok])
        ys = np.array([p[1] for _, p in ok])
        x0, x1 = 0.0, float(xs.max()) * 1.1 or 1.0
        pad = (float(ys.max() - ys.min()) or abs(float(ys.max())) or 1.0) * 0.15
        y0, y1 = float(ys.min()) - pad, float(ys.max()) + pad

        def to_px(x: float, y: float) -> tuple[int, int]:
            return (
                int(round(L + (x - x0) / (x1 - x0) * (W - L - R))),
                int(round(H - B - (y - y0) / (y1 - y0) * (H - T - B))),
            )

        for k in range(6):
            xv, yv = x0 + (x1 - x0) * k / 5, y0 + (y1 - y0) * k / 5
            px, _ = to_px(xv, y0)
            _, py = to_px(x0, yv)
            cv2.line(img, (px, T), (px, H - B), grey, 1)
            cv2.line(img, (L, py), (W - R, py), grey, 1)
            cv2.putText(img, f"{xv:.2g}", (px - 12, H - B + 20), font, 0.45, black, 1, cv2.LINE_AA)
            cv2.putText(img, f"{yv:.3g}", (8, py + 5), font, 0.45, black, 1, cv2.LINE_AA)
        front = sorted((pts[i] for i, _ in ok if rows[i].pareto), key=lambda p: p[0])
        for a, b in zip(front, front[1:]):
            cv2.line(img, to_px(*a), to_px(*b), red, 2, cv2.LINE_AA)
        for i, p in ok:
            c = to_px(*p)
            cv2.circle(img, c, 6 if rows[i].pareto else 4, red if rows[i].pareto else blue, -1, cv2.LINE_AA)
            s = rows[i].setting
            tag = (
                f"{s.size}/{'d' if s.conf_threshold is None else f'{s.conf_threshold:g}'}/{s.refine_steps}/{s.quality}"
            )
            fails = int(rows[i].summary.get("failed", 0) or 0)
            tag += "" if s.matcher == DEFAULT_MATCHER else f"/{s.matcher}"
            tag += f" ({fails} failed)" if fails else ""
            (tw, _), _ = cv2.getTextSize(tag, font, 0.4, 1)
            x = c[0] + 7 if c[0] + 7 + tw < W - R else c[0] - 7 - tw  # keep labels inside the frame
            cv2.putText(img, tag, (x, c[1] - 6), font, 0.4, black, 1, cv2.LINE_AA)
    else:
        cv2.putText(img, "no finished setting", (L, H // 2), font, 0.7, red, 1, cv2.LINE_AA)
    cv2.rectangle(img, (L, T), (W - R, H - B), black, 1)
    cv2.putText(img, "reconstruction time per pair (s)", (W // 2 - 140, H - B + 42), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(
        img,
        f"{metric} ({'higher' if METRICS[metric] else 'lower'} is better)",
        (L + 5, T - 6),
        font,
        0.45,
        black,
        1,
        cv2.LINE_AA,
    )
    labels = "labels: size/tau/refine steps/quality[/matcher]"
    cv2.putText(img, labels, (W - R - 330, T - 6), font, 0.45, black, 1, cv2.LINE_AA)
    note = "time and quality on the cases every setting reconstructed; red: Pareto front (time, quality, failures)"
    cv2.putText(img, note, (L, H - B + 66), font, 0.4, grey_text, 1, cv2.LINE_AA)
    ok_enc, buf = cv2.imencode(".png", img)  # colours above are BGR
    if not ok_enc:  # pragma: no cover - PNG encoding does not fail on a valid array
        raise OutputPathError(f"{path}: could not encode the plot")
    return atomic_write_bytes(path, buf.tobytes())


def bench_json(rows: Sequence[BenchRow], metric: str) -> dict[str, Any]:
    """JSON-ready dict of a bench: the metric and every row."""
    return to_jsonable(
        {
            "metric": metric,
            "higher_is_better": METRICS[metric],
            "rows": [{"setting": asdict(r.setting), "pareto": r.pareto, "summary": r.summary} for r in rows],
        }
    )
