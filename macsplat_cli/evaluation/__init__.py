"""Evaluation of two-view reconstruction: data sets, test splits, the protocol, metrics, baselines, benches.

Layering: :mod:`macsplat_cli.datasets` (posed frames from a folder; :mod:`macsplat_cli.datasets.coverage`,
Splatt3R's visibility mask and pairwise coverage) → :mod:`.splits` (test cases by coverage or view
angle) → :mod:`.reconstructors` (what reconstructs a case: the engine with a backend, or the
ground truth) → :mod:`.protocol` (measuring a case and a run, into :mod:`.results`) → :mod:`.summary`
(the tables) and :mod:`.result_files` (the files written as the run goes) →
:mod:`.bench` (a grid of settings and its Pareto front). :mod:`.metrics` and
:mod:`.baselines` hold the measures. The CLI commands ``macsplat eval`` and
``macsplat bench`` only parse options and draw progress and tables.
"""

from __future__ import annotations

from ..datasets import EvalDataset, EvalScene, Frame, detect_layout, load_dataset
from .baselines import PointsConfig, nearest_context, point_cloud, render_points
from .bench import BenchRow, BenchSetting, bench_markdown, bench_plot, grid, pareto_front, run_bench
from .metrics import depth_metrics, image_metrics, pose_auc, splatt3r_psnr
from .protocol import evaluate, evaluate_case
from .reconstructors import (
    BACKENDS,
    EngineReconstructor,
    OracleReconstructor,
    Reconstructor,
    ReconstructSettings,
    make_reconstructor,
)
from .result_files import ResultWriter
from .results import CaseResult, EvalConfig, EvalRun
from .splits import SPLITS, CaseSelection, EvalCase, SplitConfig, load_cases, make_cases, parse_splits
from .summary import summarize

__all__ = [
    "BACKENDS",
    "SPLITS",
    "BenchRow",
    "BenchSetting",
    "CaseResult",
    "CaseSelection",
    "EngineReconstructor",
    "EvalCase",
    "EvalConfig",
    "EvalDataset",
    "EvalRun",
    "EvalScene",
    "Frame",
    "OracleReconstructor",
    "PointsConfig",
    "ReconstructSettings",
    "Reconstructor",
    "ResultWriter",
    "SplitConfig",
    "bench_markdown",
    "bench_plot",
    "depth_metrics",
    "detect_layout",
    "evaluate",
    "evaluate_case",
    "grid",
    "image_metrics",
    "load_cases",
    "load_dataset",
    "make_cases",
    "make_reconstructor",
    "nearest_context",
    "pareto_front",
    "parse_splits",
    "point_cloud",
    "pose_auc",
    "render_points",
    "run_bench",
    "splatt3r_psnr",
    "summarize",
]
