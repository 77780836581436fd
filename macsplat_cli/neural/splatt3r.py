"""Load an official Splatt3R checkpoint into a frozen :class:`~.backbone.MASt3RBackbone` and a
:class:`~.gaussian_head.GaussianHead`.

Layout (see ``models/splatt3r.md``): a Lightning ``.ckpt`` whose ``state_dict`` holds ``encoder.`` + MASt3R
keys and ``encoder.downstream_head{1,2}.gaussian_dpt.dpt.*``; ``lpips_criterion.*`` (its training loss) and
``decoder.*`` are ignored. The file is read and checked as :mod:`.checkpoints` reads MASt3R's: a restricted
``torch.load``, strict keys and shapes (:class:`~.checkpoints.CheckpointError` names the first bad key).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import torch

from .._state_dict import log_sha256
from .backbone import MASt3RBackbone
from .checkpoints import (
    CheckpointError,
    CheckpointNotFoundError,
    LoadReport,
    build_and_load,
    tensor_dict,
    torch_load_restricted,
)
from .config import BackboneConfig, GaussianHeadConfig
from .gaussian_head import GaussianHead

__all__ = ["SPLATT3R_FILE", "SPLATT3R_HF_REPO", "load_splatt3r", "read_splatt3r_checkpoint"]

logger = logging.getLogger(__name__)

SPLATT3R_FILE = "epoch=19-step=1200.ckpt"
SPLATT3R_HF_REPO = "https://huggingface.co/brandonsmart/splatt3r_v1.0"
_SPLATT3R_HINT = (
    f"macsplat needs the Splatt3R checkpoint {SPLATT3R_FILE} from {SPLATT3R_HF_REPO}; licence CC BY-NC 4.0, "
    "non-commercial use only (see models/splatt3r.md)"
)
_SPLATT3R_IGNORED_PREFIXES = ("lpips_criterion.", "decoder.")


def read_splatt3r_checkpoint(
    path: Path | str,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], tuple[str, ...], tuple[str, ...]]:
    """Split a Splatt3R Lightning checkpoint's ``state_dict``.

    Returns ``(backbone_sd, gaussian_sd, ignored_keys, other_keys)``: MASt3R keys and
    ``downstream_head{1,2}.gaussian_dpt.*`` keys with the ``encoder.`` prefix removed, the ignored
    LPIPS/renderer keys, and keys of no known group.
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointNotFoundError(f"Splatt3R checkpoint not found: {path}. {_SPLATT3R_HINT}", path=path)
    if path.is_dir():
        raise CheckpointError(f"{path} is a folder; give the Splatt3R .ckpt file itself. {_SPLATT3R_HINT}", path=path)
    ckpt = torch_load_restricted(path, what="Splatt3R checkpoint")
    if not isinstance(ckpt, Mapping) or "state_dict" not in ckpt:
        raise CheckpointError(
            f"{path} is not a Lightning checkpoint (no 'state_dict' entry); a MASt3R .pth loads with load_mast3r",
            path=path,
        )
    sd = tensor_dict(ckpt["state_dict"], path, "Splatt3R checkpoint")
    backbone: dict[str, torch.Tensor] = {}
    gaussian: dict[str, torch.Tensor] = {}
    ignored: list[str] = []
    other: list[str] = []
    for k, v in sd.items():
        if k.startswith("encoder."):
            key = k[len("encoder.") :]
            (gaussian if ".gaussian_dpt." in key else backbone)[key] = v
        elif k.startswith(_SPLATT3R_IGNORED_PREFIXES):
            ignored.append(k)
        else:
            other.append(k)
    if ignored:
        logger.debug("%s: %d LPIPS/renderer key(s) ignored", path.name, len(ignored))
    return backbone, gaussian, tuple(ignored), tuple(other)


def load_splatt3r(
    path: Path | str,
    *,
    backbone_config: BackboneConfig | None = None,
    head_config: GaussianHeadConfig | None = None,
    strict: bool = True,
) -> tuple[MASt3RBackbone, GaussianHead, LoadReport]:
    """Build the frozen MASt3R backbone and the Gaussian head from a Splatt3R ``.ckpt`` (eval mode, CPU).

    Args:
        path: the Lightning checkpoint.
        backbone_config: architecture; default: the released MASt3R size built as Splatt3R does
            (``head_type='gaussian_head'``, ``desc_conf_mode=('exp', 1, inf)``: it omits that argument).
            The checkpoint's own config is an OmegaConf object, which is not read.
        head_config: default: ``K`` (SH coefficients per channel) from the shape of the head's last
            convolution, offsets on.
        strict: as :func:`load_mast3r`; keys outside ``encoder.``, ``lpips_criterion.`` and ``decoder.``
            count as unexpected.
    """
    path = Path(path)
    backbone_sd, gaussian_sd, ignored, other = read_splatt3r_checkpoint(path)
    if other and strict:
        raise CheckpointError(
            f"{path}: unexpected key {other[0]!r} (not under 'encoder.', 'lpips_criterion.' or 'decoder.')",
            path=path,
            key=other[0],
            file_shape=None,
            unexpected_keys=other,
        )
    if not gaussian_sd:
        raise CheckpointError(
            f"{path} has no 'encoder.downstream_head1.gaussian_dpt.*' weights: not a Splatt3R checkpoint", path=path
        )
    digest = log_sha256(path, logger, "Splatt3R checkpoint")
    bcfg = backbone_config or BackboneConfig(head_type="gaussian_head", desc_conf_mode=("exp", 1.0, float("inf")))
    if head_config is None:
        last = gaussian_sd.get("downstream_head1.gaussian_dpt.dpt.head.4.weight")
        n = int(last.shape[0]) if last is not None else 14
        if (n - 11) % 3 or (n - 11) // 3 not in (1, 4, 9, 16):
            raise CheckpointError(
                f"{path}: gaussian_dpt predicts {n} channels, which is not 11 + 3·K for K in (1, 4, 9, 16)",
                path=path,
                key="encoder.downstream_head1.gaussian_dpt.dpt.head.4.weight",
                file_shape=tuple(last.shape) if last is not None else None,
            )
        head_config = GaussianHeadConfig(sh_coeffs=(n - 11) // 3)
    hcfg = head_config
    backbone, b_missing, b_unexp, notes = build_and_load(
        lambda: MASt3RBackbone(bcfg), backbone_sd, path=path, strict=strict, key_prefix="encoder."
    )
    head, h_missing, h_unexp, h_notes = build_and_load(
        lambda: GaussianHead(bcfg, hcfg), gaussian_sd, path=path, strict=strict, key_prefix="encoder."
    )
    report = LoadReport(
        path,
        "splatt3r-ckpt",
        missing_keys=tuple("encoder." + k for k in (*b_missing, *h_missing)),
        unexpected_keys=tuple("encoder." + k for k in (*b_unexp, *h_unexp)) + other,
        ignored_keys=ignored,
        notes=tuple(notes + h_notes),
        sha256=digest,
    )
    assert isinstance(backbone, MASt3RBackbone) and isinstance(head, GaussianHead)
    return backbone.eval(), head.eval(), report
