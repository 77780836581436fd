"""Stage 7's settings (:class:`RefineConfig`, :data:`AUTO_STEPS`), apart from the refinement itself
(:mod:`.refine`): the engine, the presets and the CLI read them on every run, and importing them must not load the
renderer (its Numba kernels are imported by the background compilation thread, beside the first stages).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ..mac import MACConfig

__all__ = ["AUTO_STEPS", "RefineConfig"]

AUTO_STEPS = 25
"""``--refine auto``: the elbow of time against held-out error (benchmarks/history/refine.md)."""


@dataclass
class RefineConfig:
    """Args:
    steps: most optimisation steps; 0: no refinement (the engine skips the stage). ``--refine auto``:
        :data:`AUTO_STEPS`.
    scale: pool the maps ``scale × scale`` and render the photos at 1/scale (1 to 4; 2: about 4× faster per step
        than full resolution).
    use_mac: add the MAC loss (False: the "w/o MAC" ablation).
    lpips_weights: the LPIPS-VGG weights folder (``--lpips-weights``); the engine loads it and passes the model
        to :func:`~.refine.refine` (its term is :data:`~.refine.LPIPS_WEIGHT` × LPIPS).
    mac_matches: "filtered": the verified sparse matches (the paper's filtered matching);
        "dense": also every :data:`~.refine.DENSE_STRIDE`-th measured pixel of view 0 paired with its
        depth-consistent pixel in view 1.
    mac: MAC loss weights; ``mac.weight`` is λ_MAC.
    plateau_window: steps over which the improvement is measured.
    plateau_tol: stop when the running-mean loss improved by less than this fraction.
    min_steps: never stop before this many steps.
    coarse: ``(scale, steps)`` the refinement takes instead of ``scale`` and ``steps`` where the photos' Gaussians
        agree with each other less at ``scale`` than pooled (``best`` on three photos or more: full resolution or
        1/2, :func:`~macsplat_cli.presets.refine_for_agreement`); None: ``scale`` and ``steps`` as they are. Set by
        :func:`~macsplat_cli.presets.configure`.
    """

    steps: int = 0
    scale: int = 2
    use_mac: bool = True
    lpips_weights: Path | None = None
    mac_matches: Literal["filtered", "dense"] = "filtered"
    mac: MACConfig = field(default_factory=MACConfig)
    plateau_window: int = 25
    plateau_tol: float = 2e-3
    min_steps: int = 25
    coarse: tuple[int, int] | None = None
