"""What produces the reconstruction of a test case: a backend of the pipeline, or the ground truth.

A :class:`Reconstructor` is any callable ``(scene, case, settings) → Reconstruction`` with a
``name``; it sees the two context frames (and, for the oracle only, their ground truth).
The evaluation measures whatever it returns, so backends plug in through :data:`BACKENDS`
(``--backend`` choices): a factory from :class:`BackendOptions` to a reconstructor.
``classical`` is the weight-free pipeline; ``neural`` the network (user-supplied weights).

:class:`OracleReconstructor` builds the reconstruction from ground truth — the true
relative pose and the true depth of both context views fed to the classical Gaussian
stage — to check the evaluation itself (a perfect reconstruction must score a 0° pose
error and render the scene as the photos show it). It is not a ``--backend`` choice.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

import numpy as np

from ..cameras import CameraSet, Scale, save_cameras
from ..errors import InputError, ReconstructionError
from ..pipeline.gaussian_init import GaussianInitConfig, gaussians_from_depth
from ..pipeline.run import Pipeline, ReconstructConfig, Reconstruction
from ..pipeline.types import DepthMap, Matches, TwoViewGeometry
from ..pipeline.views import ViewConfig, load_views
from .datasets import EvalScene
from .splits import EvalCase

__all__ = [
    "BACKENDS",
    "BackendOptions",
    "ClassicalReconstructor",
    "IntrinsicsMode",
    "NeuralReconstructor",
    "OracleReconstructor",
    "ReconstructSettings",
    "Reconstructor",
    "make_reconstructor",
]

logger = logging.getLogger(__name__)

IntrinsicsMode = Literal["given", "estimated"]


@dataclass
class ReconstructSettings:
    """What the evaluation fixes for every reconstructor.

    Args:
        size: long side of the working images (the pipeline's ``--size``); targets are
            rendered at the same working size.
        intrinsics: ``"given"``: the ground-truth intrinsics of the context photos are
            passed (``--intrinsics``); ``"estimated"``: none (EXIF, prior, self-calibration).
    """

    size: int = 512
    intrinsics: IntrinsicsMode = "given"


class Reconstructor(Protocol):
    """Reconstructs the two context frames of a case (may raise ReconstructionError)."""

    name: str

    def __call__(self, scene: EvalScene, case: EvalCase, settings: ReconstructSettings) -> Reconstruction: ...


@dataclass
class BackendOptions:
    """Backend settings swept by ``macsplat bench`` (each backend uses those that apply).

    Args:
        conf_threshold: τ of the filtered matching (None: the default).
        refine_steps: test-time refinement steps (0: off).
        refine_scale: refinement resolution divisor.
        neural: the neural backend's files and device (keyword arguments of
            :func:`macsplat_cli.pipeline.neural.load_neural_models`).
    """

    conf_threshold: float | None = None
    refine_steps: int = 0
    refine_scale: int = 2
    neural: dict[str, str | Path | None] = field(default_factory=dict)


def _context_paths(scene: EvalScene, case: EvalCase) -> list[Path]:
    return [scene.frames[c].image for c in case.context]


@dataclass
class ClassicalReconstructor:
    """The weight-free pipeline (:class:`~macsplat_cli.pipeline.run.Pipeline`), optionally refined."""

    options: BackendOptions = field(default_factory=BackendOptions)
    name: str = "classical"

    def pipeline(self, config: ReconstructConfig) -> Pipeline:
        return Pipeline(config)

    def base_config(self) -> ReconstructConfig:
        return ReconstructConfig()

    def __call__(self, scene: EvalScene, case: EvalCase, settings: ReconstructSettings) -> Reconstruction:
        config = self.base_config()
        config.views = ViewConfig(size=settings.size)
        if self.options.conf_threshold is not None:
            config.matching.conf_threshold = self.options.conf_threshold
        paths = _context_paths(scene, case)
        with tempfile.TemporaryDirectory(prefix="macsplat-eval-") as tmp:
            if settings.intrinsics == "given":
                cams = [scene.frames[c].camera for c in case.context]
                named = [dataclasses.replace(cam, name=p.name) for cam, p in zip(cams, paths)]
                config.views.intrinsics = Path(tmp) / "intrinsics.json"
                save_cameras(config.views.intrinsics, CameraSet(named))
            rec = self.pipeline(config).run(paths)
        if self.options.refine_steps > 0:
            rec = _refined(rec, self.options.refine_steps, self.options.refine_scale)
        return rec


@dataclass
class NeuralReconstructor(ClassicalReconstructor):
    """The neural backend (:mod:`macsplat_cli.pipeline.neural`); the networks load once, at construction,
    so that a missing or mismatched checkpoint stops the run before any case."""

    name: str = "neural"

    def __post_init__(self) -> None:
        from ..pipeline.neural import NeuralBackend, load_neural_models

        self.backend = NeuralBackend(load_neural_models(**self.options.neural))

    def base_config(self) -> ReconstructConfig:
        from ..pipeline.neural import neural_reconstruct_config

        return neural_reconstruct_config()

    def pipeline(self, config: ReconstructConfig) -> Pipeline:
        from ..pipeline.neural import NeuralPipeline

        return NeuralPipeline(self.backend, config)


def _refined(rec: Reconstruction, steps: int, scale: int) -> Reconstruction:
    from ..refine import RefineConfig, refine

    out = refine(rec.views, rec.geometry, rec.maps, RefineConfig(steps=steps, scale=scale))
    report = {**rec.report, "refine": {"steps": out.steps, "seconds": out.seconds, "scale": scale}}
    return dataclasses.replace(rec, maps=out.maps, report=report)


@dataclass
class OracleReconstructor:
    """Ground-truth geometry through the classical Gaussian stage (for testing the evaluation).

    Args:
        scale: ``"metric"`` keeps the scene's units; ``"relative"`` divides lengths by the
            true baseline (baseline 1), as the classical pipeline does, so the evaluation's
            rescaling of the target cameras is exercised.
        gaussians: settings of the Gaussian stage.
    """

    scale: Scale = "metric"
    gaussians: GaussianInitConfig = field(default_factory=GaussianInitConfig)
    name: str = "oracle"

    def __call__(self, scene: EvalScene, case: EvalCase, settings: ReconstructSettings) -> Reconstruction:
        views = load_views(_context_paths(scene, case), ViewConfig(size=settings.size, use_exif=False))
        cams = [scene.frames[c].camera for c in case.context]
        T = cams[1].world_to_cam @ cams[0].cam_to_world
        s = 1.0 / float(np.linalg.norm(T[:3, 3])) if self.scale == "relative" else 1.0
        depths = []
        for k, (v, c) in enumerate(zip(views, case.context)):
            v.K = cams[k].rescaled(v.width, v.height).K.copy()
            v.intrinsics_source = "file"
            d = scene.depth(c, (v.width, v.height))
            if d is None:
                raise ReconstructionError(
                    f"the oracle needs ground-truth depth, and frame {scene.frames[c].name} has none"
                )
            depths.append(DepthMap(d * np.float32(s), (d > 0).astype(np.float32)))
        empty = np.zeros((0, 2))
        no_matches = Matches(empty, empty, np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))
        geometry = TwoViewGeometry(T[:3, :3].copy(), T[:3, 3] * s, views[0].K, views[1].K, no_matches, {})
        maps = gaussians_from_depth(views, geometry, depths, self.gaussians)
        report = {"backends": {"all": "oracle (ground truth)"}, "times_s": {}}
        return Reconstruction(views, geometry, depths, maps, report, scale=self.scale)


BackendFactory = Callable[[BackendOptions], Reconstructor]
BACKENDS: dict[str, BackendFactory] = {
    "classical": lambda options: ClassicalReconstructor(options),
    "neural": lambda options: NeuralReconstructor(options),
}
"""``--backend`` name → factory."""


def make_reconstructor(backend: str, options: BackendOptions | None = None) -> Reconstructor:
    """The reconstructor of a registered backend.

    Raises:
        InputError: unknown backend name.
    """
    factory = BACKENDS.get(backend)
    if factory is None:
        raise InputError(f"unknown backend {backend!r}; available: {', '.join(sorted(BACKENDS))}")
    return factory(options or BackendOptions())
