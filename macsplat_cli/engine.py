"""The engine: the one place that assembles a reconstruction.

``reconstruct(images, config) -> Reconstruction`` loads the models a configuration needs, builds
the pipeline's stages (classical, or neural around a :class:`~macsplat_cli.neural.predictor.PairPredictor`),
runs them, refines the Gaussians when asked, and fills the typed report. ``macsplat reconstruct``,
``eval``, ``bench`` and the benchmarks all go through it; they only map their options to an
:class:`EngineConfig` and write files.

Loading is separate (:func:`load_models`) so that a caller reconstructing many pairs — the
evaluation, the bench grid — loads the networks once::

    config = EngineConfig(backend="neural", neural=NeuralOptions(weights="mast3r.pth"))
    models = load_models(config)  # every file checked here, before any work
    for a, b in pairs:
        rec = reconstruct([a, b], config, models=models)
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError
from .pipeline.run import Pipeline, ReconstructConfig, Reconstruction, StageEvent, count_gaussians
from .report import RefineReport

__all__ = [
    "BACKENDS",
    "QUALITIES",
    "WORKING_SIZE",
    "EngineConfig",
    "Models",
    "NeuralOptions",
    "RefineOptions",
    "build_pipeline",
    "load_models",
    "reconstruct",
]

logger = logging.getLogger(__name__)

BACKENDS = ("classical", "neural")
"""The reconstruction backends (``--backend``)."""
QUALITIES = ("fast", "balanced", "best")
"""The ``--quality`` presets."""
WORKING_SIZE = {"fast": 384, "balanced": 512, "best": 512}
"""The working long side each preset uses when the caller does not set one (``--size``)."""
FAST_SIFT = (640, 8000)
"""``--quality fast``, classical backend: SIFT's detection size and most keypoints (the defaults: 768, 8000)."""
RefineEvent = Callable[[int, dict[str, float]], None]


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
    device: str = "cpu"
    precision: str = "fp32"

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
class RefineOptions:
    """Test-time refinement (``--refine``): ``steps`` 0 is off; ``scale`` the resolution divisor;
    ``use_mac`` False is the "w/o MAC" ablation; ``lpips_weights`` adds LPIPS to the loss."""

    steps: int = 0
    scale: int = 2
    use_mac: bool = True
    lpips_weights: Path | None = None


@dataclass
class EngineConfig:
    """Everything a reconstruction depends on.

    Args:
        backend: ``"classical"`` (no learned weights) or ``"neural"``.
        quality: ``"fast"``, ``"balanced"`` or ``"best"``: how much of the scene's redundancy the
            compaction removes (:meth:`~macsplat_cli.compact.CompactConfig.preset`); ``"fast"`` also detects
            SIFT on a smaller image (:data:`FAST_SIFT`) and leaves out the depth's slanted-plane refinement
            (``DepthConfig.slanted_iters``). The CLI picks the working size from it when ``--size``
            is not given (:data:`WORKING_SIZE`).
        budget: at most this many Gaussians in the scene (None: no limit).
        pipeline: the stages' settings (working size and intrinsics in ``pipeline.views``).
        conf_threshold: τ of the filtered matching; None: the backend's default (0.04 classical, 1 neural).
        neural: the neural backend's files and device.
        refine: test-time refinement.
    """

    backend: str = "classical"
    pipeline: ReconstructConfig = field(default_factory=ReconstructConfig)
    conf_threshold: float | None = None
    neural: NeuralOptions = field(default_factory=NeuralOptions)
    refine: RefineOptions = field(default_factory=RefineOptions)
    quality: str = "balanced"
    budget: int | None = None

    def validate(self, *, files: bool = True) -> None:
        """Usage errors, before any work (``files=False``: the models are given, no checkpoint is needed).

        Raises:
            InputError: an unknown backend, device or precision; neural options with the classical
                backend; the neural backend without weights; ``dino`` without ``fusion`` (or the reverse);
                LPIPS weights without refinement; a bad threshold or refinement setting.
        """
        from .neural.predictor import MISSING_WEIGHTS_HELP, check_fusion_files, resolve_device

        name = self.backend
        if name not in BACKENDS:
            raise InputError(f"--backend {self.backend!r}: use {' or '.join(BACKENDS)}")
        n = self.neural
        if n.device not in ("cpu", "cuda"):
            raise InputError(f"--device {n.device!r}: use cpu or cuda")
        if n.precision not in ("fp32", "bf16"):
            raise InputError(f"--precision {n.precision!r}: use fp32 or bf16")
        if name == "classical" and n.given:
            raise InputError(f"{', '.join(n.given)} only apply to --backend neural")
        onnx = name == "neural" and self.neural.is_onnx
        if onnx:
            others = [flag for flag in n.given if flag in ("--gaussian-head", "--dino", "--fusion", "--precision")]
            if others:
                raise InputError(
                    f"{n.weights} is an ONNX predictor: it holds its own Gaussian head and fusion and computes in the "
                    f"precision it was exported with (export-onnx --fp16/--quantize); drop {', '.join(others)}"
                )
            from .neural.onnx_runtime import ort_providers

            ort_providers(n.device)  # CUDA asked for where onnxruntime has no CUDA provider
        elif name == "neural":
            resolve_device(n.device)  # CUDA asked for where there is none
        if name == "neural" and files and not onnx:
            if n.weights is None and n.gaussian_head is None:
                raise InputError(MISSING_WEIGHTS_HELP)
            check_fusion_files(n.dino, n.fusion)
        if self.conf_threshold is not None and not (math.isfinite(self.conf_threshold) and self.conf_threshold >= 0):
            raise InputError(f"--conf-threshold {self.conf_threshold}: give a finite number ≥ 0")
        if self.quality not in QUALITIES:
            raise InputError(f"--quality {self.quality!r}: use {', '.join(QUALITIES)}")
        if self.budget is not None and (isinstance(self.budget, bool) or not isinstance(self.budget, int)
                                        or self.budget < 1):  # fmt: skip
            raise InputError(f"--budget {self.budget!r}: give a positive number of Gaussians")
        r = self.refine
        if r.steps < 0:
            raise InputError(f"--refine {r.steps}: give a number of steps (0 = off) or 'auto'")
        if not 1 <= r.scale <= 4:
            raise InputError(f"--refine-scale {r.scale}: use 1 to 4")
        if r.lpips_weights is not None and r.steps == 0:
            raise InputError("--lpips-weights is used by the refinement: add --refine STEPS or --refine auto")

    def replace(self, **changes: Any) -> EngineConfig:
        """A deep copy with some fields replaced (configs are mutable; runs never share one)."""
        return dataclasses.replace(copy.deepcopy(self), **changes)


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


def load_models(config: EngineConfig) -> Models:
    """Load (and check) every file the configuration names; the configuration is validated first.

    Raises:
        InputError: a usage error (:meth:`EngineConfig.validate`).
        CheckpointNotFoundError, CheckpointError, DINOv3CheckpointError, FusionCheckpointError,
        LPIPSWeightsError: a missing file, or one that does not fit.
    """
    config.validate()
    return _load_models(config)


def _load_models(config: EngineConfig) -> Models:
    """:func:`load_models` for a configuration already validated."""
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
    if config.refine.lpips_weights is not None:
        from .lpips import load_lpips

        models.lpips = load_lpips(config.refine.lpips_weights)
    models.load_s = time.perf_counter() - t0
    return models


def build_pipeline(config: EngineConfig, models: Models) -> Pipeline:
    """The pipeline of a (validated) configuration, its stages around the loaded models."""
    pipe_cfg = copy.deepcopy(config.pipeline)
    if config.backend == "neural":
        from .pipeline.neural import NeuralConfig, neural_reconstruct_config, neural_stages

        if models.predictor is None:
            raise ValueError("the neural backend needs models.predictor (load_models)")
        pipe_cfg = neural_reconstruct_config(pipe_cfg)
        if config.conf_threshold is not None:
            pipe_cfg.matching.conf_threshold = config.conf_threshold
        # --quality fast: DINOv3 and the fusion run only when the backbone's descriptors verify too few matches
        fusion = "auto" if config.quality == "fast" else "always"
        neural = NeuralConfig(precision=config.neural.precision, fusion=fusion)  # type: ignore[arg-type]
        # onnxruntime takes and returns CPU arrays whatever its provider; torch runs where it was asked to
        device = "cpu" if config.neural.is_onnx else config.neural.device
        stages = neural_stages(models.predictor, pipe_cfg, neural, device)
        return Pipeline(pipe_cfg, scale="metric", **stages)
    if config.conf_threshold is not None:
        pipe_cfg.matching.conf_threshold = config.conf_threshold
    if config.quality == "fast":  # SIFT on a smaller image (4,000 keypoints at 512 px cost pose accuracy at 45°)
        d = pipe_cfg.descriptors
        pipe_cfg.descriptors = dataclasses.replace(
            d, detect_size=min(d.detect_size, FAST_SIFT[0]), max_keypoints=min(d.max_keypoints, FAST_SIFT[1])
        )
        # no slanted-plane PatchMatch in the depth: 0.15 s at 1 MP for ±0.3 dB
        pipe_cfg.depth = dataclasses.replace(pipe_cfg.depth, slanted_iters=0)
    return Pipeline(pipe_cfg)


def reconstruct(
    images: Sequence[str | Path],
    config: EngineConfig | None = None,
    *,
    models: Models | None = None,
    on_stage: StageEvent | None = None,
    on_refine_step: RefineEvent | None = None,
) -> Reconstruction:
    """Reconstruct a Gaussian scene from two photos.

    Args:
        images: the two photos; the first defines the world frame.
        config: the settings (default: the classical backend, no refinement).
        models: models loaded by :func:`load_models` for this configuration (loaded here when None,
            reported as the ``"weights"`` stage).
        on_stage: called with ``(stage, "start" | "end" | "fail")`` around every stage (progress display).
        on_refine_step: called after each refinement step with the step and its loss terms.

    Returns:
        The :class:`~macsplat_cli.pipeline.run.Reconstruction`, its typed report filled (``neural`` and
        ``refine`` sections when they apply).

    Raises:
        InputError: bad settings, photos or intrinsics.
        ReconstructionError: the scene cannot be reconstructed (the message says why).
    """
    config = config or EngineConfig()
    notify = on_stage or (lambda stage, event: None)
    if models is None:
        config.validate()
        needs_loading = config.backend == "neural" or config.refine.lpips_weights is not None
        if needs_loading:
            notify("weights", "start")
        try:
            models = _load_models(config)  # validated above, before any stage event
        except BaseException:
            if needs_loading:
                notify("weights", "fail")
            raise
        if needs_loading:
            notify("weights", "end")
    else:
        config.validate(files=False)
    pipeline = build_pipeline(config, models)
    rec = pipeline.run(images, on_stage=on_stage)
    if config.backend == "neural":
        predictor = models.predictor
        rec.report.backends["network"] = f"{predictor.network_name()} on {config.neural.device}"
        rec.report.backends["fusion"] = predictor.fusion_name()
        rec.report.neural = {**pipeline.pair.report(), "files": dict(models.files), "load_s": models.load_s}
        fusion = rec.report.neural["fusion"]
        if fusion.get("policy") == "auto" and fusion["applied"]:  # it ran on demand: were its matches better?
            fusion["matches_kept"] = "fused" if rec.report.fallback_used else "unfused (the fused ones verified fewer)"
    if config.refine.steps > 0:
        rec = _refine(rec, config.refine, models, notify, on_refine_step)
    return _compact(rec, config, notify)


def _layer_size(rec: Reconstruction) -> int:
    """Gaussians of the far background layer (:mod:`.pipeline.background`), 0 without one."""
    layer = rec.background.gaussians if rec.background is not None else None
    return len(layer) if layer is not None else 0


def _compact(rec: Reconstruction, config: EngineConfig, notify: StageEvent) -> Reconstruction:
    """The scene without what it does not need (``quality``, ``budget``), reported step by step."""
    from .compact import CompactConfig, compact_reconstruction

    n_layer = _layer_size(rec)
    budget, background = config.budget, rec.background
    if budget is not None and n_layer:
        if n_layer * 2 > budget:  # the far layer would take most of a small budget: the scene needs it more
            logger.info("--budget %d: the far background layer (%d Gaussians) is left out", budget, n_layer)
            background, n_layer = None, 0
        else:  # --budget bounds what is written: the layer counts
            budget -= n_layer
    notify("compact", "start")
    try:
        gaussians, compact_report = compact_reconstruction(rec, CompactConfig.preset(config.quality, budget=budget))
    except BaseException:
        notify("compact", "fail")
        raise
    notify("compact", "end")
    report = copy.copy(rec.report)
    report.compact = compact_report.to_dict()
    report.gaussians = len(gaussians) + n_layer
    report.add_time("compact", compact_report.seconds)
    logger.info("compaction (%s): %s", config.quality, compact_report.summary())
    return dataclasses.replace(rec, report=report, compacted=gaussians, background=background)


def _refine(
    rec: Reconstruction, options: RefineOptions, models: Models, notify: StageEvent, on_step: RefineEvent | None
) -> Reconstruction:
    from .refine import RefineConfig, refine

    h, w = rec.maps[0].size
    f = options.scale
    if any(m.size[0] % f or m.size[1] % f for m in rec.maps):
        raise InputError(f"--refine-scale {f}: the working size {w}x{h} is not divisible by it")
    cfg = RefineConfig(steps=options.steps, scale=f, use_mac=options.use_mac)
    notify("refine", "start")
    try:
        out = refine(rec.views, rec.geometry, rec.maps, cfg, depths=rec.depths, lpips=models.lpips, on_step=on_step)
    except BaseException:
        notify("refine", "fail")
        raise
    notify("refine", "end")
    report = copy.copy(rec.report)
    report.refine = RefineReport(
        steps=out.steps,
        max_steps=options.steps,
        stopped_early=out.stopped_early,
        seconds=out.seconds,
        scale=f,
        mac=options.use_mac,
        lpips=models.lpips is not None,
        loss_first=out.history[0],
        loss_last=out.history[-1],
    )
    report.add_time("refine", out.seconds)
    report.gaussians = count_gaussians(out.maps) + _layer_size(rec)
    return dataclasses.replace(rec, maps=out.maps, report=report)
