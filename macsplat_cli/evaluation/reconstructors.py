"""What produces the reconstruction of a test case: the engine with a backend, or the ground truth.

A :class:`Reconstructor` is any callable ``(scene, case, settings) → Reconstruction`` with a
``name``; it sees the context frames (two, or more with ``--context-views``; and, for the oracle only, their
ground truth).
The evaluation measures whatever it returns, so backends plug in through :data:`BACKENDS`
(``--backend`` choices): a factory from an :class:`~macsplat_cli.engine.EngineConfig` to a
reconstructor. ``classical`` and ``neural`` are :class:`EngineReconstructor`: the engine
(:func:`macsplat_cli.engine.reconstruct`), the same code as ``macsplat reconstruct``, with the
models loaded once.

:class:`OracleReconstructor` builds the reconstruction from ground truth — the true
relative poses and the true depth of the context views fed to the classical Gaussian
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

from .. import __version__
from ..cameras import CameraSet, Scale, save_cameras
from ..datasets import EvalScene
from ..engine import EngineConfig, Models, load_models, reconstruct
from ..errors import InputError, ReconstructionError
from ..gaussians import GaussianMaps
from ..pipeline.gaussian_init import GaussianInitConfig, gaussians_from_depth, view_gaussians
from ..pipeline.run import Reconstruction, count_gaussians
from ..pipeline.types import DepthMap, Matches, TwoViewGeometry, View
from ..pipeline.views import ViewConfig, load_views
from ..report import RunReport
from .splits import EvalCase

__all__ = [
    "BACKENDS",
    "EngineReconstructor",
    "IntrinsicsMode",
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
    """Reconstructs the context frames of a case (may raise ReconstructionError)."""

    @property
    def name(self) -> str:
        """The backend's name, as ``--backend`` gives it."""

    def __call__(self, scene: EvalScene, case: EvalCase, settings: ReconstructSettings) -> Reconstruction: ...


def _context_paths(scene: EvalScene, case: EvalCase) -> list[Path]:
    return [scene.frames[c].image for c in case.context]


@dataclass
class EngineReconstructor:
    """A backend through the engine. The models load once, at construction, so that a missing or
    mismatched checkpoint stops the run before any case (pass ``models`` to share them).

    Args:
        config: the engine settings (backend, quality, overrides, neural files), resolved by the same
            :func:`~macsplat_cli.presets.configure` as ``macsplat reconstruct``'s; the working size and the intrinsics
            come from each case's :class:`ReconstructSettings`.
        models: models already loaded for ``config`` (:func:`~macsplat_cli.engine.load_models`).
    """

    config: EngineConfig = field(default_factory=EngineConfig)
    models: Models | None = None

    def __post_init__(self) -> None:
        if self.models is None:
            self.models = load_models(self.config)
        else:
            self.config.validate(files=False)

    @property
    def name(self) -> str:
        return self.config.backend

    def __call__(self, scene: EvalScene, case: EvalCase, settings: ReconstructSettings) -> Reconstruction:
        config = self.config.replace()
        config.pipeline.views = ViewConfig()
        config.overrides = dataclasses.replace(config.overrides, size=settings.size)
        paths = _context_paths(scene, case)
        with tempfile.TemporaryDirectory(prefix="macsplat-eval-") as tmp:
            if settings.intrinsics == "given":
                cams = [scene.frames[c].camera for c in case.context]
                named = [dataclasses.replace(cam, name=p.name) for cam, p in zip(cams, paths)]
                config.pipeline.views.intrinsics = Path(tmp) / "intrinsics.json"
                save_cameras(config.pipeline.views.intrinsics, CameraSet(named))
            return reconstruct(paths, config, models=self.models)


@dataclass
class OracleReconstructor:
    """Ground-truth geometry through the classical Gaussian stage (for testing the evaluation).

    The cameras' ``poses`` in context view 0's frame (no pose search: ``pose`` None); more than two context views
    give every photo registered in the report's ``multiview`` section, as the multi-view pipeline's.

    Args:
        scale: ``"metric"`` keeps the scene's units; ``"relative"`` divides lengths by the
            true baseline of context views 0 and 1 (baseline 1), as the classical pipeline does, so the
            evaluation's rescaling of the target cameras is exercised.
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
        if len(views) > 2:
            poses = [cams[0].world_to_cam @ c.cam_to_world for c in cams]  # in camera 0's frame
            for P in poses:
                P[:3, 3] *= s
            maps = [view_gaussians(v, d, v.K, P, self.gaussians) for v, d, P in zip(views, depths, poses)]
            photos = [{"name": v.name, "registered": True} for v in views]
            report = self._report(views, depths, maps, {"photos": photos, "registered": len(views)})
            return Reconstruction(views, poses, depths, maps, report, scale=self.scale)
        empty = np.zeros((0, 2))
        no_matches = Matches(empty, empty, np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))
        geometry = TwoViewGeometry(T[:3, :3].copy(), T[:3, 3] * s, views[0].K, views[1].K, no_matches, {})
        maps = gaussians_from_depth(views, geometry, depths, self.gaussians)
        poses = [geometry.cam_to_world(0), geometry.cam_to_world(1)]
        return Reconstruction(views, poses, depths, maps, self._report(views, depths, maps), scale=self.scale)

    def _report(
        self, views: list[View], depths: list[DepthMap], maps: list[GaussianMaps], multiview: dict | None = None
    ) -> RunReport:
        return RunReport(
            macsplat_version=__version__,
            inputs=[str(v.path) for v in views],
            backends={"all": "oracle (ground truth)"},
            times_s={},
            images=[],
            keypoints=[0] * len(views),
            fallback_used=False,
            matches={},
            inlier_ratio=None,
            pose={},
            depth_coverage=[float(d.valid.mean()) for d in depths],
            depth_measured=[None] * len(views),
            gaussians=count_gaussians(maps),
            config={},
            scale=self.scale,
            multiview=multiview,
        )


BackendFactory = Callable[[EngineConfig, Models | None], Reconstructor]
BACKENDS: dict[str, BackendFactory] = {
    "classical": EngineReconstructor,
    "neural": EngineReconstructor,
}
"""``--backend`` name → factory ``(config, models or None) → reconstructor``."""


def make_reconstructor(config: EngineConfig, models: Models | None = None) -> Reconstructor:
    """The reconstructor of ``config.backend`` (a registered backend), with ``models`` if already loaded.

    Raises:
        InputError: unknown backend name; any error of :func:`~macsplat_cli.engine.load_models`.
    """
    factory = BACKENDS.get(config.backend)
    if factory is None:
        raise InputError(f"unknown backend {config.backend!r}; available: {', '.join(sorted(BACKENDS))}")
    return factory(config, models)
