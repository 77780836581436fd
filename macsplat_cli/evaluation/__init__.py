"""Evaluation of reconstruction from two (or more) context views: data sets, test splits, the protocol, metrics,
baselines, benches.

Layering: :mod:`macsplat_cli.datasets` (posed frames from a folder; :mod:`macsplat_cli.datasets.coverage`,
Splatt3R's visibility mask and pairwise coverage) → :mod:`.splits` (test cases by coverage or view
angle) → :mod:`.contexts` (more than two context views per case) → :mod:`.reconstructors` (what reconstructs a
case: the engine with a backend, or the ground truth) → :mod:`.protocol` (measuring a case and a run, into
:mod:`.results`; :mod:`.alignment`: the pose errors and the frame of more than two context views) →
:mod:`.summary` (the tables) and :mod:`.result_files` (the files written as the run goes) →
:mod:`.bench` (a grid of settings and its Pareto front) → :mod:`.commands` (the entry points: :func:`run`,
:func:`benchmark`, :func:`select`, one spec each). :mod:`.metrics` and
:mod:`.baselines` hold the measures. The CLI commands ``macsplat eval`` and
``macsplat bench`` only parse options and draw progress and tables.
"""

from __future__ import annotations

from ..datasets import EvalDataset, EvalScene, Frame, detect_layout, load_dataset
from .alignment import Similarity, aligned_camera, fit_similarity, pairwise_pose_errors
from .baselines import PointsConfig, nearest_context, point_cloud, render_points
from .bench import BenchRow, BenchSetting, bench_markdown, bench_plot, grid, pareto_front, run_bench
from .commands import BenchSpec, CaseSpec, EvalOutcome, EvalProgress, EvalSpec, benchmark, run, select
from .contexts import check_context_views, extend_case, extend_cases
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
    "BenchSpec",
    "CaseSpec",
    "CaseResult",
    "CaseSelection",
    "EngineReconstructor",
    "EvalCase",
    "EvalConfig",
    "EvalDataset",
    "EvalOutcome",
    "EvalProgress",
    "EvalRun",
    "EvalScene",
    "EvalSpec",
    "Frame",
    "OracleReconstructor",
    "PointsConfig",
    "ReconstructSettings",
    "Reconstructor",
    "ResultWriter",
    "Similarity",
    "SplitConfig",
    "aligned_camera",
    "bench_markdown",
    "bench_plot",
    "benchmark",
    "check_context_views",
    "depth_metrics",
    "detect_layout",
    "evaluate",
    "evaluate_case",
    "extend_case",
    "extend_cases",
    "fit_similarity",
    "grid",
    "image_metrics",
    "load_cases",
    "load_dataset",
    "make_cases",
    "make_reconstructor",
    "nearest_context",
    "pairwise_pose_errors",
    "pareto_front",
    "parse_splits",
    "point_cloud",
    "pose_auc",
    "render_points",
    "run",
    "run_bench",
    "select",
    "splatt3r_psnr",
    "summarize",
]
