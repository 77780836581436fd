"""The library entry point of ``macsplat train``: :func:`train` runs one :class:`TrainSpec` (the data, the model to
start from, and the run's :class:`~.config.TrainConfig`), checked before anything is read or written.

What a caller shows while the run goes is a :class:`TrainProgress`; this module draws nothing (the CLI passes its
Rich bar and prints the closing line from the returned :class:`TrainOutcome`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from .._atomic import check_writable
from ..errors import InputError
from .config import TrainConfig
from .model import Init, ModelKind, ModelSpec, build_training_model, freeze_for_training
from .trainer import Trainer, TrainResult

if TYPE_CHECKING:
    from ..datasets import Layout
    from ..lpips import LPIPS
    from ..neural.predictor import PairPredictor

__all__ = ["RUN_FILES", "TrainOutcome", "TrainProgress", "TrainSpec", "train"]

logger = logging.getLogger(__name__)

RUN_FILES = ("run.json", "metrics.csv", "last.pt", "best.pt")
"""What a run writes into its folder (each checked writable before the data and the model load)."""


class TrainProgress(Protocol):
    """What a caller shows while the run trains (on the process of rank 0 only)."""

    def start(self, total: int, step: int, about: str) -> None:
        """The run folder is ready: ``total`` steps from ``step`` (a resumed run's); ``about``: the run on one
        line."""
        ...

    def step(self, step: int, row: dict[str, float]) -> None:
        """After each optimiser step: its metrics (``loss``, ``mac``, ...)."""
        ...

    def stop(self) -> None:
        """The run ended (finished, interrupted or failed)."""
        ...


class Silent:
    """The :class:`TrainProgress` that shows nothing (a library caller's default)."""

    def start(self, total: int, step: int, about: str) -> None:
        pass

    def step(self, step: int, row: dict[str, float]) -> None:
        pass

    def stop(self) -> None:
        pass


@dataclass
class TrainSpec:
    """One training run (``macsplat train``).

    Args:
        data: posed images (ScanNet++ root, generic folder, CO3D, ICL).
        config: every setting of the run (a recipe's values, the options that replaced some of them).
        overridden: the options that replaced the recipe's values (``run.json`` names them).
        layout: the data's layout (``auto``: detect it).
        scenes: only these scenes (None: all).
        split: ScanNet++: the training split list (validation: ``nvs_sem_val`` when present).
        coverage: covisibility range ``(low, high)`` of the context pairs.
        val_pairs: held-out pairs (without a validation split).
        model: architecture of a random init (``tiny`` or ``full``).
        init: ``weights`` (start from the files below) or ``random`` (the backbone trains too).
        weights: MASt3R checkpoint, or a macsplat checkpoint.
        gaussian_head: Splatt3R checkpoint.
        dino: DINOv3 weights for the semantic fusion.
        no_dino: no DINOv3 fusion (ablation).
        lpips_weights: LPIPS-VGG weights (None: D-SSIM in the photometric loss).
        train_backbone: unfreeze the MASt3R backbone.
        resume: continue the run in ``config.out`` from its ``last.pt``.
        force: start over in a run folder that holds another run.
    """

    data: Path
    config: TrainConfig
    overridden: list[str] = dataclasses.field(default_factory=list)
    layout: Layout = "auto"
    scenes: list[str] | None = None
    split: str = "nvs_sem_train"
    coverage: tuple[float, float] = (0.3, 1.0)
    val_pairs: int = 8
    model: ModelKind = "full"
    init: Init = "weights"
    weights: Path | None = None
    gaussian_head: Path | None = None
    dino: Path | None = None
    no_dino: bool = False
    lpips_weights: Path | None = None
    train_backbone: bool = False
    resume: bool = False
    force: bool = False


@dataclass
class TrainOutcome:
    """What :func:`train` did: the loop's result, and whether this process reports (rank 0)."""

    result: TrainResult
    is_main: bool


def _check(spec: TrainSpec) -> None:
    """The options' values and combinations, before anything is read."""
    if spec.init == "weights" and spec.weights is None and spec.gaussian_head is None:
        raise InputError(
            "--init weights needs --weights (MASt3R) or --gaussian-head (Splatt3R); or train from scratch with "
            "--init random (--model tiny trains in minutes on a CPU)"
        )
    if spec.resume and spec.force:
        raise InputError("--resume and --force contradict each other: give one")
    mac_weight = spec.config.loss.mac_weight
    if not (mac_weight >= 0 and not math.isnan(mac_weight)):
        raise InputError(f"--mac-weight {mac_weight}: give a number ≥ 0")


def _lpips(spec: TrainSpec) -> LPIPS | None:
    """The LPIPS model of ``spec.lpips_weights``; None (D-SSIM instead, said in the log) without."""
    if spec.lpips_weights is None:
        loss = spec.config.loss
        logger.info("no --lpips-weights: the photometric loss uses D-SSIM (weight %g) instead of LPIPS (%g)",
                    loss.ssim_weight, loss.lpips_weight)  # fmt: skip
        return None
    from ..lpips import load_lpips

    return load_lpips(spec.lpips_weights)


def _model(spec: TrainSpec, config: TrainConfig) -> tuple[PairPredictor, bool]:
    """The predictor to train, frozen but for what trains, and whether its backbone trains (a random one does,
    with a point-map regression on ground-truth depth: ``config.loss.geometry_weight`` set)."""
    model = ModelSpec(
        model=spec.model, init=spec.init, weights=spec.weights, gaussian_head=spec.gaussian_head, dino=spec.dino,
        no_dino=spec.no_dino, seed=config.seed, dino_variant=config.dino_variant, max_scale=config.max_scale,
    )  # fmt: skip
    train_backbone = spec.train_backbone
    if spec.init == "random":  # a random backbone has no geometry to keep: it learns it, from ground-truth depth
        train_backbone = True
        config.loss.geometry_weight = 1.0
        logger.info("--init random: the backbone trains too, with a point-map regression on ground-truth depth")
    return freeze_for_training(build_training_model(model), train_backbone=train_backbone), train_backbone


def train(spec: TrainSpec, progress: TrainProgress | None = None) -> TrainOutcome:
    """Train the predictor of ``spec`` into ``spec.config.out`` (``run.json``, ``metrics.csv``, ``last.pt``,
    ``best.pt``); on many processes under torchrun (DDP; rank 0 writes).

    Raises:
        InputError, DatasetError, OutputPathError: bad options, data or run folder, before the loop starts.
    """
    from ..neural.predictor import resolve_device
    from .data import PairSamplingConfig
    from .recipes import recipe_record
    from .setup import load_training_data

    progress = progress or Silent()
    _check(spec)
    config = spec.config
    resolve_device(config.device)
    if config.loss.mac_weighting == "c0c1" and config.loss.mac_weight > 0 and not spec.no_dino:
        logger.info("match weights c0·c1 (the paper's): the fusion module gets no gradient from MAC, and no other "
                    "term trains it")  # fmt: skip
    config.validate()
    for name in RUN_FILES:  # before the data and the model load
        check_writable(config.out / name)
    lpips = _lpips(spec)
    sampling = PairSamplingConfig(
        coverage=spec.coverage, targets=config.targets, size=config.size, crop=config.crop, per_scene=config.per_scene
    )
    train_data, val_data, info = load_training_data(
        spec.data, layout=spec.layout, split=spec.split, scenes=spec.scenes, sampling=sampling,
        val_pairs=spec.val_pairs, seed=config.seed, exclude=config.exclude_scenes,
    )  # fmt: skip
    steps = config.steps_for(info["scenes"], int(os.environ.get("WORLD_SIZE", "1")))
    config = dataclasses.replace(config, steps=steps, loss=dataclasses.replace(config.loss))
    config.validate()
    predictor, train_backbone = _model(spec, config)
    n_train = sum(p.numel() for p in predictor.parameters() if p.requires_grad)
    files = {"weights": spec.weights, "gaussian_head": spec.gaussian_head, "dino": spec.dino}
    options = {"model": spec.model, "init": spec.init, "no_dino": spec.no_dino, "train_backbone": train_backbone}
    run_info = {"recipe": recipe_record(config, spec.overridden), "data": info,
                "model": {**options, **files, "trainable_parameters": n_train}}  # fmt: skip
    trainer = Trainer(predictor, train_data, val_data, config, lpips=lpips, run_info=run_info, on_step=progress.step)
    main = trainer.ctx.is_main
    trainer.prepare_run_folder(resume=spec.resume, force=spec.force)
    try:
        if main:
            progress.start(
                config.steps, trainer.step,
                f"recipe {config.recipe}: {info['train_pairs']} training pair(s), {info['val_pairs']} validation "
                f"pair(s) from {info['scenes']} scene(s); {config.steps} step(s); {n_train:,} trainable parameters; "
                f"{trainer.ctx.world_size} process(es)",
            )  # fmt: skip
        return TrainOutcome(trainer.fit(), main)
    finally:
        if main:
            progress.stop()
