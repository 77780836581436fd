"""Stage 7's entry: the refinement a reconstruction takes (``--refine``, ``--quality best``).

Two photos: the per-view maps on both photos with the MAC loss, the cameras fixed (:mod:`.refine`). More photos
(registered, no LPIPS term): the Gaussians and the poses together over every photo (:mod:`.multiview.joint`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..report import RefineReport
from .refine import RefineConfig, RefineResult, RefineStep, check_scale, refine_reconstruction

if TYPE_CHECKING:
    import torch

    from .run import Reconstruction

__all__ = ["check_scale", "refine_stage"]


def refine_stage(
    rec: Reconstruction, config: RefineConfig, *, lpips: torch.nn.Module | None = None,
    on_step: RefineStep | None = None,
) -> tuple[RefineResult, RefineReport]:  # fmt: skip
    """The refinement of ``rec`` (module docstring) and its report section; ``RefineResult.poses`` is set when the
    poses were refined.

    Raises:
        InputError: the working size is not divisible by ``config.scale`` (:func:`check_scale`).
    """
    if rec.multiview is None or rec.poses is None or lpips is not None:
        return refine_reconstruction(rec, config, lpips=lpips, on_step=on_step)
    from .multiview.joint import joint_reconstruction

    check_scale(rec.maps, config.scale)
    return joint_reconstruction(rec, config, rec.multiview.match_sets(), on_step)
