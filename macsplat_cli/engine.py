"""The engine: the one place that assembles a reconstruction.

``reconstruct(images, config) -> Reconstruction`` loads the models a configuration needs, turns the configuration
into every stage's settings once (:func:`~macsplat_cli.presets.configure`), builds the pipeline's stages
(classical, or neural around a :class:`~macsplat_cli.neural.predictor.PairPredictor`), runs them, refines the
Gaussians when asked (stage 7), compacts them (stage 8), and the report gets each stage's section as it finishes.
:func:`render_path` renders the novel views along the path between the two cameras. ``macsplat reconstruct``,
``eval``, ``bench`` and the benchmarks all go through it; they only map their options to an :class:`EngineConfig`
and write files.

Loading is separate (:func:`load_models`) so that a caller reconstructing many pairs loads the networks once::

    config = EngineConfig(backend="neural", neural=NeuralOptions(weights="mast3r.pth"))
    models = load_models(config)  # every file checked here, before any work
    for a, b in pairs:
        rec = reconstruct([a, b], config, models=models)
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .pipeline import warmup
from .pipeline.refine_config import RefineConfig
from .pipeline.run import (
    Pipeline,
    ReconstructConfig,
    Reconstruction,
    StageClock,
    StageEvent,
    classical_stages,
    count_gaussians,
)  # fmt: skip
from .pipeline.views import ViewConfig
from .presets import (
    DEFAULT_MATCHER,
    DEVICES,
    PRECISIONS,
    Backend,
    Device,
    Matcher,
    Overrides,
    Precision,
    Quality,
    StageSettings,
    assert_never,
    check_choice,
    check_choices,
    configure,
    resolved_refine_steps,
)

__all__ = [
    "EngineConfig",
    "Models",
    "NeuralOptions",
    "build_pipeline",
    "load_models",
    "reconstruct",
    "path_views",
    "render_path",
]

logger = logging.getLogger(__name__)

RefineEvent = Callable[[int, int, dict[str, float]], None]


@dataclass
class NeuralOptions:
    """The neural backend's files and where/how it runs.

    Args:
        weights: MASt3R checkpoint (``.pth`` or Hugging Face folder), a macsplat checkpoint (``.pt``), or an
            exported predictor (``.onnx``, run by onnxruntime; it holds the head and the fusion too).
        gaussian_head: Splatt3R checkpoint (``.ckpt``); alone it also provides the backbone.
        dino: DINOv3 weights (semantic fusion; needs ``fusion``).
        fusion: Residual Semantic Fusion weights (needs ``dino``).
        device: ``"cpu"`` or ``"cuda"``.
        precision: ``"fp32"`` or ``"bf16"`` (autocast).
    """

    weights: Path | None = None
    gaussian_head: Path | None = None
    dino: Path | None = None
    fusion: Path | None = None
    device: Device = "cpu"
    precision: Precision = "fp32"

    def files(self) -> dict[str, Path]:
        """The files given, by role (``weights``, ``gaussian_head``, ``dino``, ``fusion``)."""
        roles = {"weights": self.weights, "gaussian_head": self.gaussian_head, "dino": self.dino, "fusion": self.fusion}
        return {k: Path(v) for k, v in roles.items() if v is not None}

    @property
    def is_onnx(self) -> bool:
        """``weights`` is an exported ONNX predictor (by its extension), run by onnxruntime."""
        return self.weights is not None and Path(self.weights).suffix.lower() == ".onnx"

    @property
    def given(self) -> list[str]:
        """The options set away from their defaults, as command-line flags."""
        flags = [f"--{k.replace('_', '-')}" for k in self.files()]
        flags += ["--device"] if self.device != "cpu" else []
        return flags + (["--precision"] if self.precision != "fp32" else [])


@dataclass
class EngineConfig:
    """Everything a reconstruction depends on: the user's choices, turned into every stage's settings by
    :meth:`settings` (:func:`~macsplat_cli.presets.configure`, the one place that resolves them). No field here
    holds a value a stage field also holds: the working size, τ, the budget and the refinement's steps are
    :class:`~macsplat_cli.presets.Overrides` of the preset, and ``pipeline`` / ``refine`` hold only what no preset
    sets (:meth:`validate` refuses a preset-owned value set there).

    Args:
        backend: ``"classical"`` (no learned weights) or ``"neural"``.
        quality: ``"fast"``, ``"balanced"`` or ``"best"``: the working size, how light the stages are, whether the
            Gaussians are refined and how much of the scene's redundancy the compaction removes
            (:mod:`macsplat_cli.presets`).
        overrides: ``--size``, ``--conf-threshold``, ``--budget``, ``--refine``, ``--refine-scale`` (None: preset's).
        pipeline: the stages' settings to start from: the inputs (intrinsics, poses, far layer, low-confidence
            acceptance) and research settings; ``views.size`` and ``matching.conf_threshold`` stay at their
            defaults (``overrides`` sets them).
        neural: the neural backend's files and device.
        refine: how the refinement runs (MAC, LPIPS); ``steps`` and ``scale`` stay at their defaults (``overrides``
            or the quality's, :func:`~macsplat_cli.presets.refine_steps` and ``refine_scale``).
        matcher: ``--matcher``, ``"sift"``, ``"auto"`` or ``"aliked"`` (:func:`~macsplat_cli.presets.learned_search`)
    """

    backend: Backend = "classical"
    quality: Quality = "balanced"
    overrides: Overrides = field(default_factory=Overrides)
    pipeline: ReconstructConfig = field(default_factory=ReconstructConfig)
    neural: NeuralOptions = field(default_factory=NeuralOptions)
    refine: RefineConfig = field(default_factory=RefineConfig)
    matcher: Matcher = DEFAULT_MATCHER

    def validate(self, *, files: bool = True, photos: int = 2) -> None:
        """Usage errors of a run on ``photos`` photos, before any work (``files=False``: the models are given, no
        checkpoint is needed). Only values are checked; CUDA is checked when the models load (:func:`load_models`).

        Raises:
            InputError: a bad device or precision; what :func:`~macsplat_cli.presets.check_choices` refuses; neural
                options with the classical backend; the neural backend without weights or with ``dino`` and no
                ``fusion`` (or the reverse); LPIPS without steps; a preset-owned value in ``pipeline``/``refine``.
        """
        n = self.neural
        check_choice("--device", n.device, DEVICES)
        check_choice("--precision", n.precision, PRECISIONS)
        check_choices(self.quality, self.backend, self.matcher, self.overrides)  # configure's own checks
        if self.backend == "classical" and n.given:
            raise InputError(f"{', '.join(n.given)} only apply to --backend neural")
        onnx = self.backend == "neural" and n.is_onnx
        if onnx:
            others = [flag for flag in n.given if flag in ("--gaussian-head", "--dino", "--fusion", "--precision")]
            if others:
                raise InputError(
                    f"{n.weights} is an ONNX predictor: it holds its own Gaussian head and fusion and computes in the "
                    f"precision it was exported with (export-onnx --fp16/--quantize); drop {', '.join(others)}"
                )
        if self.backend == "neural" and files and not onnx:
            _check_neural_files(n)
        _check_owned(self.pipeline, self.refine)
        _check_refine(self.refine, resolved_refine_steps(self.quality, self.overrides, photos))

    def settings(self, photos: int = 2) -> StageSettings:
        """Every stage's settings for ``photos`` photos: the quality preset, the backend and the overrides applied
        once."""
        return configure(
            self.quality, self.backend, self.overrides, pipeline=self.pipeline, refine=self.refine,
            precision=self.neural.precision, matcher=self.matcher, photos=photos,
        )  # fmt: skip

    def replace(self, **changes: Any) -> EngineConfig:
        """A deep copy with some fields replaced (configs are mutable; runs never share one)."""
        return dataclasses.replace(copy.deepcopy(self), **changes)


def _check_neural_files(n: NeuralOptions) -> None:
    """The neural backend's files as given (not read): weights or a Gaussian head; DINOv3 and fusion together."""
    if n.weights is None and n.gaussian_head is None:
        from .neural.predictor import MISSING_WEIGHTS_HELP  # the loader's own message, imported to raise it

        raise InputError(MISSING_WEIGHTS_HELP)
    if (n.dino is None) != (n.fusion is None):
        from .neural.predictor import check_fusion_files  # the loader's own message, imported to raise it

        check_fusion_files(n.dino, n.fusion)


def _check_owned(pipeline: ReconstructConfig, refine: RefineConfig) -> None:
    """The stage fields :func:`~macsplat_cli.presets.configure` sets from the preset and the overrides are left at
    their defaults in the caller's settings: one owner each (``EngineConfig.overrides``)."""
    from .pipeline.matching import MatchConfig

    owned = [("pipeline.views.size", pipeline.views.size, ViewConfig.size, "size", "--size"),
             ("pipeline.matching.conf_threshold", pipeline.matching.conf_threshold, MatchConfig.conf_threshold,
              "conf_threshold", "--conf-threshold"),
             ("refine.steps", refine.steps, RefineConfig.steps, "refine", "--refine"),
             ("refine.scale", refine.scale, RefineConfig.scale, "refine_scale", "--refine-scale")]  # fmt: skip
    for name, value, default, override, flag in owned:
        if value != default:
            raise InputError(f"{name} {value}: set it with EngineConfig.overrides.{override} ({flag})")


def _check_refine(r: RefineConfig, steps: int) -> None:
    """How the refinement runs, given the ``steps`` it will run."""
    if r.lpips_weights is not None and steps == 0:
        raise InputError("--lpips-weights is used by the refinement: add --refine STEPS or --refine auto")


@dataclass
class Models:
    """What :func:`load_models` loaded for a configuration, reusable across reconstructions.

    Attributes:
        predictor: the network (neural backend), on its device in eval mode; None for classical.
        lpips: the LPIPS model for the refinement, or None.
        files: the checkpoint of each role.
        load_s: seconds spent loading.
    """

    predictor: Any = None
    lpips: Any = None
    files: dict[str, str] = field(default_factory=dict)
    load_s: float = 0.0


def load_models(config: EngineConfig, photos: int = 2) -> Models:
    """Load (and check) every file the configuration names; the configuration is validated first (for runs on
    ``photos`` photos), then the machine (CUDA for ``--device cuda``).

    Raises:
        InputError: a usage error (:meth:`EngineConfig.validate`), or ``--device cuda`` where torch (or onnxruntime,
            for an ONNX predictor) has no CUDA.
        CheckpointNotFoundError, CheckpointError, DINOv3CheckpointError, FusionCheckpointError,
        LPIPSWeightsError: a missing file, or one that does not fit.
    """
    config.validate(photos=photos)
    _check_device(config)
    return _load_models(config)


def _check_device(config: EngineConfig) -> None:
    """``--device cuda`` where the neural backend's runtime has no CUDA: the usage error, before any file is read."""
    if config.backend != "neural":
        return
    n = config.neural
    if n.is_onnx:
        from .neural.onnx_runtime import ort_providers

        ort_providers(n.device)  # CUDA asked for where onnxruntime has no CUDA provider
    else:
        from .neural.predictor import resolve_device

        resolve_device(n.device)  # CUDA asked for where there is none


def _load_models(config: EngineConfig) -> Models:
    """:func:`load_models` for a configuration already validated (and its device checked)."""
    t0 = time.perf_counter()
    models = Models()
    if config.backend == "neural":
        from .neural.loading import load_pair_predictor
        from .neural.predictor import resolve_device

        files = config.neural.files()
        if config.neural.is_onnx:
            from .neural.onnx_runtime import OnnxPairPredictor

            models.predictor = OnnxPairPredictor(files["weights"], device=config.neural.device)
        else:
            models.predictor = load_pair_predictor(**files).to(resolve_device(config.neural.device))
        models.files = {k: str(v) for k, v in files.items()}
    if config.refine.lpips_weights is not None:  # only with steps (validate)
        from .lpips import load_lpips

        models.lpips = load_lpips(config.refine.lpips_weights)
    models.load_s = time.perf_counter() - t0
    return models


def build_pipeline(config: EngineConfig, models: Models, photos: int = 2) -> Pipeline:
    """The pipeline of a (validated) configuration for ``photos`` photos, its stages around the loaded models."""
    return _build_pipeline(config, config.settings(photos=photos), models)


def _build_pipeline(config: EngineConfig, settings: StageSettings, models: Models) -> Pipeline:
    """The pipeline of the backend's stages: :func:`~.pipeline.run.classical_stages` or, around the loaded
    network, :func:`~.pipeline.neural.neural_stages`."""
    backend = config.backend
    if backend == "classical":
        return Pipeline(settings.pipeline, classical_stages(settings.pipeline))
    if backend == "neural":
        from .pipeline.neural import neural_stages

        if models.predictor is None:
            raise ValueError("the neural backend needs models.predictor (load_models)")
        # onnxruntime takes and returns CPU arrays whatever its provider; torch runs where it was asked to
        device = "cpu" if config.neural.is_onnx else config.neural.device
        return Pipeline(settings.pipeline, neural_stages(models.predictor, settings.pipeline, settings.neural, device))
    assert_never(backend)


def _models_for(config: EngineConfig, models: Models | None, clock: StageClock, photos: int) -> Models:
    """The given models (the configuration for ``photos`` photos checked against them), or the configuration's,
    loaded as the ``"weights"`` stage when there is something to load."""
    if models is not None:
        config.validate(files=False, photos=photos)
        return models
    config.validate(photos=photos)
    _check_device(config)  # before the weights stage starts: a usage error, not a failed stage
    if config.backend == "neural" or config.refine.lpips_weights is not None:
        return clock("weights", lambda: _load_models(config))
    return _load_models(config)


def reconstruct(
    images: Sequence[str | Path],
    config: EngineConfig | None = None,
    *,
    models: Models | None = None,
    on_stage: StageEvent | None = None,
    on_refine_step: RefineEvent | None = None,
) -> Reconstruction:
    """Reconstruct a Gaussian scene from two or more photos (more than two: :mod:`.pipeline.multiview`).

    Args:
        images: the photos (2 to ``_limits.MAX_PHOTOS``); the first (registered) one defines the world frame.
        config: the settings (default: the classical backend, no refinement).
        models: models loaded by :func:`load_models` for this configuration (loaded here when None,
            reported as the ``"weights"`` stage).
        on_stage: called with ``(stage, "start" | "end" | "fail")`` around every stage (progress display).
        on_refine_step: called after each refinement step with the step, the most steps and its loss terms.

    Returns:
        The :class:`~macsplat_cli.pipeline.run.Reconstruction`, its typed report filled (``neural``,
        ``refine`` and ``compact`` sections when they apply).

    Raises:
        InputError: bad settings, photos or intrinsics.
        ReconstructionError: the scene cannot be reconstructed (the message says why).
    """
    config = config or EngineConfig()
    clock = StageClock(on_stage)  # the stages around the pipeline's (its own clock times stages 1-6)
    _check_photos(images, config)
    warmup.compile_in_background(len(images))
    models = _models_for(config, models, clock, len(images))
    settings = config.settings(photos=len(images))
    pipeline = _build_pipeline(config, settings, models)
    rec = pipeline.run(images, on_stage=on_stage)
    if config.backend == "neural":
        _add_network(rec, pipeline, config, models)
    if settings.refine.steps > 0:
        rec = _refine(rec, settings.refine, models, clock, on_refine_step)
    return _compact(rec, settings, clock)


def _check_photos(images: Sequence[str | Path], config: EngineConfig) -> None:
    """The photo count, and what more than two photos cannot have yet (the neural backend): before any weights
    load, the one place that checks them (the CLI and :meth:`~.pipeline.run.Pipeline.run` leave it here).

    Raises:
        InputError: fewer than 2 or too many photos; more than two, or given poses, with the neural backend.
    """
    from ._limits import check_photo_count

    check_photo_count(len(images))
    if len(images) == 2 and config.pipeline.multiview.poses is None:
        return
    what = f"{len(images)} photos" if len(images) > 2 else "--poses"
    if config.backend == "neural":
        raise InputError(
            f"{what}: the neural backend reconstructs two photos at its own poses (pairwise global alignment is not "
            "built yet); use --backend classical"
        )


def _add_network(rec: Reconstruction, pipeline: Pipeline, config: EngineConfig, models: Models) -> None:
    """The neural backend's section of the report: the network, its pass and what the fusion did."""
    from .pipeline.neural import NeuralPair

    predictor, pair = models.predictor, pipeline.pair
    assert isinstance(pair, NeuralPair)  # the neural backend's pair slot (neural_stages)
    section = dataclasses.replace(pair.report(), files=dict(models.files), load_s=models.load_s)
    fusion = section.fusion
    if fusion.policy == "auto" and fusion.applied:  # it ran on demand: were its matches better?
        fusion.matches_kept = "fused" if rec.report.fallback_used else "unfused (the fused ones verified fewer)"
    rec.report.add_network(f"{predictor.network_name()} on {config.neural.device}", predictor.fusion_name(), section)


def _layer_size(rec: Reconstruction) -> int:
    """Gaussians of the far background layer (:mod:`.pipeline.background`), 0 without one."""
    layer = rec.background.gaussians if rec.background is not None else None
    return len(layer) if layer is not None else 0


def _refine(
    rec: Reconstruction, config: RefineConfig, models: Models, clock: StageClock, on_step: RefineEvent | None
) -> Reconstruction:
    """Stage 7 on the pipeline's maps; the refined maps replace them."""
    from .pipeline.refine_stage import check_scale, refine_stage

    check_scale(rec.maps, config.scale)  # a usage error, before the stage starts
    warmup.wait_for_renderer()  # a first run: the renderer's kernels come from their own process
    out, section = clock("refine", lambda: refine_stage(rec, config, lpips=models.lpips, on_step=on_step))
    rec.report.add_refine(section, count_gaussians(out.maps) + _layer_size(rec))
    return dataclasses.replace(rec, maps=out.maps, poses=rec.poses if out.poses is None else out.poses)


def _compact(rec: Reconstruction, settings: StageSettings, clock: StageClock) -> Reconstruction:
    """Stage 8: the scene without what it does not need (the quality's compaction, ``--budget`` bounding the scene
    written, the far layer included), reported step by step."""
    from .pipeline.compact import compact_reconstruction

    n_layer = _layer_size(rec)
    background, compact = rec.background, settings.compact
    budget = compact.budget
    if budget is not None and n_layer:
        if n_layer * 2 > budget:  # the far layer would take most of a small budget: the scene needs it more
            logger.info("--budget %d: the far background layer (%d Gaussians) is left out", budget, n_layer)
            background, n_layer = None, 0
        else:  # --budget bounds what is written: the layer counts
            compact = dataclasses.replace(compact, budget=budget - n_layer)
    gaussians, report = clock("compact", lambda: compact_reconstruction(rec, compact))
    rec.report.add_compact(report, len(gaussians) + n_layer)
    logger.info("compaction (%s): %s", compact.name, report.summary())
    return dataclasses.replace(rec, compacted=gaussians, background=background)


def path_views(rec: Reconstruction, n: int) -> Iterator[np.ndarray]:
    """``n`` novel views of the scene along the path between the two cameras (both included), at the working size,
    each yielded as soon as it is rendered (a caller that writes them holds one at a time).

    The cameras' rotations are slerped and their centres and intrinsics interpolated
    (:func:`~macsplat_cli.trajectory.interpolate_cameras`); each view is rendered on the scene's device.

    Yields:
        ``n`` images ``[H, W, 3] uint8`` (what ``--renders`` and ``--video`` write).
    """
    import torch

    from .images import to_uint8
    from .render import render_camera
    from .trajectory import interpolate_cameras

    path = interpolate_cameras(list(rec.cameras(original_size=False)), n)
    warmup.wait_for_renderer()
    for cam in path:
        with torch.no_grad():
            frame = to_uint8(render_camera(rec.gaussians, cam).rgb)
        yield frame


def render_path(rec: Reconstruction, n: int) -> list[np.ndarray]:
    """The ``n`` views of :func:`path_views` in one list (all held in memory: for a few views).

    Returns:
        ``n`` images ``[H, W, 3] uint8``.
    """
    return list(path_views(rec, n))
