"""Neural components: a MASt3R-compatible backbone, a Splatt3R-style Gaussian head, and checkpoint loaders.

Everything here is written from the architecture descriptions in the project's reference notes;
the official MASt3R / Splatt3R checkpoints (non-commercial licences) are user-supplied files, see
``models/mast3r.md`` and ``models/splatt3r.md``. Importing this package loads no weights.
"""

from __future__ import annotations

from .backbone import BackboneView, MASt3RBackbone, conf_activation, depth_activation
from .checkpoints import (
    CheckpointError,
    CheckpointNotFoundError,
    LoadReport,
    check_state_dict,
    load_mast3r,
    read_mast3r_checkpoint,
)
from .config import BackboneConfig, GaussianHeadConfig
from .constructor import ModelConfigError, parse_constructor_string
from .gaussian_head import GaussianHead
from .rope import RoPE2D, patch_positions
from .splatt3r import load_splatt3r, read_splatt3r_checkpoint

__all__ = [
    "BackboneConfig",
    "BackboneView",
    "CheckpointError",
    "CheckpointNotFoundError",
    "GaussianHead",
    "GaussianHeadConfig",
    "LoadReport",
    "MASt3RBackbone",
    "ModelConfigError",
    "RoPE2D",
    "check_state_dict",
    "conf_activation",
    "depth_activation",
    "load_mast3r",
    "load_splatt3r",
    "parse_constructor_string",
    "patch_positions",
    "read_mast3r_checkpoint",
    "read_splatt3r_checkpoint",
]
