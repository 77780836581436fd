"""The MAC-Splat network as one tensor-in/tensor-out module: :class:`PairPredictor`.

``PairPredictor(img0, img1)`` runs the MASt3R backbone on a pair, the Residual Semantic Fusion of
the descriptors (when a DINOv3 encoder and fusion weights are loaded) and the Splatt3R Gaussian head
(when loaded). Its :meth:`~PairPredictor.forward` takes and returns tensors only — no numpy, no
timing, no device moves, no autocast — so the same module is trained (``macsplat train``), exported
(``macsplat export-onnx``) and run by the reconstruction pipeline; :meth:`~PairPredictor.predict`
wraps the output tuple into a :class:`PairPrediction`.

Input convention: RGB in [0, 1], ``[B, 3, H, W]``, ``H`` and ``W`` multiples of 16, both views the
same size. Outputs are per view, stacked on dim 1 (``[B, 2, …]``), in **view 0's camera frame**.

:func:`~.loading.load_pair_predictor` builds one from the user's official checkpoints (MASt3R, Splatt3R,
DINOv3) and macsplat fusion weights; :func:`check_fusion_files` and :func:`resolve_device` check the options
that choose them before any file is read.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from .._checks import check_shape
from ..errors import InputError, ShapeError
from ..gaussians import GaussianMaps
from .backbone import MASt3RBackbone
from .checkpoints import MAST3R_FILE, MAST3R_HF_REPO
from .dinov3 import DINOv3Encoder
from .fusion import ResidualSemanticFusion, fuse_descriptors
from .gaussian_head import GaussianHead

__all__ = [
    "MISSING_WEIGHTS_HELP",
    "PREDICTION_OUTPUTS",
    "PairPrediction",
    "PairPredictor",
    "check_fusion_files",
    "prediction_from_outputs",
    "resolve_device",
]

logger = logging.getLogger(__name__)

MISSING_WEIGHTS_HELP = (
    f"--backend neural needs the MASt3R checkpoint {MAST3R_FILE}: download it from {MAST3R_HF_REPO} "
    "(or the naver/mast3r README; licence CC BY-NC-SA 4.0, non-commercial) and pass --weights PATH, "
    "or pass a Splatt3R checkpoint with --gaussian-head (see models/mast3r.md)"
)

PREDICTION_OUTPUTS = ("pts3d", "conf", "desc", "desc_conf")
"""Names of :meth:`PairPredictor.forward`'s first outputs; with a Gaussian head, ``GAUSSIAN_OUTPUTS`` follow."""
GAUSSIAN_OUTPUTS = ("means", "log_scales", "quats", "opacity_logits", "sh")


@dataclass
class PairPrediction:
    """The network's outputs for a batch of pairs (``B`` pairs, views stacked on dim 1).

    Attributes:
        pts3d: both views' point maps in **view 0's camera frame** (metres for the metric checkpoint). [B, 2, H, W, 3]
        conf: point-map confidences (≥ 1). [B, 2, H, W]
        desc: matching descriptors, fused with DINOv3 features when the fusion ran. [B, 2, H, W, D]
        desc_conf: descriptor confidences with the activation's floor removed (``exp(x)`` ≥ 0, whether
            the backbone was built as MASt3R's checkpoint (``exp``) or as Splatt3R does (``1 + exp``)). [B, 2, H, W]
        gaussians: the Gaussian head's per-pixel Gaussians of view 0 and view 1 (both in view 0's camera
            frame), or None without a head.
    """

    pts3d: torch.Tensor
    conf: torch.Tensor
    desc: torch.Tensor
    desc_conf: torch.Tensor
    gaussians: tuple[GaussianMaps, GaussianMaps] | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) of the network grid."""
        return int(self.pts3d.shape[2]), int(self.pts3d.shape[3])

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None) -> PairPrediction:
        """A copy on ``device`` (floating tensors cast to ``dtype`` when given)."""

        def mv(t: torch.Tensor) -> torch.Tensor:
            return t.to(device=device, dtype=dtype if dtype is not None and t.is_floating_point() else t.dtype)

        gaussians = None
        if self.gaussians is not None:
            g0, g1 = (GaussianMaps(*(mv(t) for t in g.tensors())) for g in self.gaussians)
            gaussians = (g0, g1)
        return PairPrediction(mv(self.pts3d), mv(self.conf), mv(self.desc), mv(self.desc_conf), gaussians)


class PairPredictor(nn.Module):
    """MASt3R backbone (+ Residual Semantic Fusion with a frozen DINOv3) (+ Splatt3R Gaussian head).

    Args:
        backbone: the MASt3R backbone (or any module with its ``forward`` and ``config``).
        gaussian_head: Splatt3R's Gaussian head; None: no Gaussian outputs.
        dino: frozen DINOv3 encoder; with ``fusion``, the descriptors are fused.
        fusion: Residual Semantic Fusion; needs ``dino``.

    Raises:
        InputError: only one of ``dino``/``fusion``, or widths that do not fit each other.
    """

    def __init__(
        self,
        backbone: MASt3RBackbone,
        gaussian_head: GaussianHead | None = None,
        dino: DINOv3Encoder | None = None,
        fusion: ResidualSemanticFusion | None = None,
    ) -> None:
        super().__init__()
        if (dino is None) != (fusion is None):
            raise InputError("semantic fusion needs both the DINOv3 encoder and the fusion module (or neither)")
        if dino is not None and fusion is not None:
            if dino.config.embed_dim != fusion.config.dino_dim:
                raise InputError(
                    f"the fusion weights expect {fusion.config.dino_dim}-d DINOv3 features, but the DINOv3 encoder "
                    f"is {dino.config.name} ({dino.config.embed_dim}-d)"
                )
            if fusion.config.desc_dim != backbone.config.local_feat_dim:
                raise InputError(
                    f"the fusion weights are for {fusion.config.desc_dim}-d descriptors, the backbone predicts "
                    f"{backbone.config.local_feat_dim}-d ones"
                )
        self.backbone = backbone
        self.gaussian_head = gaussian_head
        self.dino = dino
        self.fusion = fusion

    # ------------------------------------------------------------------ description
    @property
    def fusion_enabled(self) -> bool:
        return self.dino is not None and self.fusion is not None

    @property
    def output_names(self) -> tuple[str, ...]:
        """Names of :meth:`forward`'s outputs, in order (Gaussian outputs: ``gaussians_<field>``, views stacked)."""
        head = tuple(f"gaussians_{n}" for n in GAUSSIAN_OUTPUTS) if self.gaussian_head is not None else ()
        return PREDICTION_OUTPUTS + head

    @property
    def desc_dim(self) -> int:
        """Width ``D`` of the matching descriptors."""
        return int(self.backbone.config.local_feat_dim)

    @property
    def has_gaussian_head(self) -> bool:
        return self.gaussian_head is not None

    @property
    def input_size(self) -> tuple[int, int] | None:
        """``(W, H)`` the predictor only accepts, or None: any multiple of 16 (a fixed-size ONNX export has one)."""
        return None

    @property
    def square_input(self) -> int | None:
        """The side of the square crops the network was trained on (MASt3R's 224 checkpoints), else None."""
        return 224 if tuple(self.backbone.config.img_size) == (224, 224) else None

    def network_name(self) -> str:
        c = self.backbone.config
        return f"mast3r (enc {c.enc_embed_dim}x{c.enc_depth}, dec {c.dec_embed_dim}x{c.dec_depth})"

    def fusion_name(self) -> str:
        if not self.fusion_enabled:
            return "skipped (no --dino/--fusion weights)"
        assert self.dino is not None
        return f"dinov3-{self.dino.config.name}+residual-semantic-fusion"

    def fusion_detail(self, size: tuple[int, int]) -> str:
        """One line for the report: what the fusion does on an ``(H, W)`` input."""
        if not self.fusion_enabled:
            return "semantic fusion skipped: no DINOv3 encoder (weights not given); descriptors unchanged"
        assert self.dino is not None and self.fusion is not None
        p = self.dino.config.patch_size
        h, w, c = size[0] // p, size[1] // p, self.dino.config.embed_dim
        return (
            f"semantic fusion applied: DINOv3 {self.dino.config.name} features {h}×{w}×{c} → "
            f"descriptors {size[0]}×{size[1]}×{self.fusion.config.desc_dim}"
        )

    # ------------------------------------------------------------------ computation
    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Tensors in, tensors out (what ONNX export and training see).

        Args:
            img0: view 0, RGB in [0, 1]. [B, 3, H, W], H and W multiples of 16
            img1: view 1, the same shape. [B, 3, H, W]

        Returns:
            ``pts3d [B, 2, H, W, 3]``, ``conf [B, 2, H, W]``, ``desc [B, 2, H, W, D]``, ``desc_conf [B, 2, H, W]``;
            with a Gaussian head also ``means [B, 2, H, W, 3]``, ``log_scales [B, 2, H, W, 3]``,
            ``quats [B, 2, H, W, 4]`` (wxyz), ``opacity_logits [B, 2, H, W]``, ``sh [B, 2, H, W, K, 3]``.
            The names are :attr:`output_names`.
        """
        return self._run(img0, img1, fuse=True)

    def forward_unfused(self, img0: torch.Tensor, img1: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """:meth:`forward` without the semantic fusion: ``desc`` is the backbone's own (DINOv3 does not run).
        :meth:`fuse_descriptors` on its ``desc`` gives :meth:`forward`'s exactly. Same arguments and outputs."""
        return self._run(img0, img1, fuse=False)

    def fuse_descriptors(self, desc: torch.Tensor, img0: torch.Tensor, img1: torch.Tensor) -> torch.Tensor:
        """The semantic fusion of :meth:`forward_unfused`'s descriptors (unchanged without DINOv3/fusion weights).

        Args:
            desc: both views' unfused descriptors. [B, 2, H, W, D]
            img0, img1: the views they come from, RGB in [0, 1]. [B, 3, H, W]

        Returns:
            The fused descriptors. [B, 2, H, W, D]
        """
        b = desc.shape[0]
        check_shape(desc, (b, 2, "H", "W", "D"), "desc")
        flat = torch.cat([desc[:, 0], desc[:, 1]])  # [2B, H, W, D], in forward's order
        x = torch.cat([img0, img1]) * 2.0 - 1.0
        fused = fuse_descriptors(flat, x, fusion=self.fusion, encoder=self.dino).desc
        return torch.stack([fused[:b], fused[b:]], 1)

    def _run(self, img0: torch.Tensor, img1: torch.Tensor, *, fuse: bool) -> tuple[torch.Tensor, ...]:
        if img0.shape != img1.shape:
            raise ShapeError("img1", tuple(img1.shape), f"the shape of img0 {list(img0.shape)}")
        x0, x1 = img0 * 2.0 - 1.0, img1 * 2.0 - 1.0  # the backbone's [-1, 1]
        out0, out1 = self.backbone(x0, x1)
        b = img0.shape[0]
        desc = torch.cat([out0.desc, out1.desc])  # [2B, H, W, D]: the fusion sees each view's own image
        if fuse:
            desc = fuse_descriptors(desc, torch.cat([x0, x1]), fusion=self.fusion, encoder=self.dino).desc
        vmin = float(self.backbone.config.desc_conf_mode[1])
        outputs = (
            torch.stack([out0.pts3d, out1.pts3d], 1),
            torch.stack([out0.conf, out1.conf], 1),
            torch.stack([desc[:b], desc[b:]], 1),
            torch.stack([out0.desc_conf, out1.desc_conf], 1).sub(vmin).clamp_min(0.0),
        )
        if self.gaussian_head is None:
            return outputs
        g0, g1 = self.gaussian_head(out0, out1, img0, img1)
        return outputs + tuple(torch.stack([a, b_], 1) for a, b_ in zip(g0.tensors(), g1.tensors()))

    def predict(self, img0: torch.Tensor, img1: torch.Tensor) -> PairPrediction:
        """:meth:`forward`, its outputs named. Same arguments."""
        return prediction_from_outputs(self(img0, img1))


def prediction_from_outputs(outputs: tuple[torch.Tensor, ...] | list[torch.Tensor]) -> PairPrediction:
    """A :class:`PairPrediction` from :meth:`PairPredictor.forward`'s output tuple (4 or 9 tensors)."""
    if len(outputs) not in (len(PREDICTION_OUTPUTS), len(PREDICTION_OUTPUTS) + len(GAUSSIAN_OUTPUTS)):
        raise ShapeError("predictor outputs", (len(outputs),), "4 or 9 tensors")
    pts3d, conf, desc, desc_conf = outputs[:4]
    gaussians = None
    if len(outputs) > 4:
        fields = outputs[4:]
        g0, g1 = (GaussianMaps(*(f[:, k] for f in fields)) for k in (0, 1))
        gaussians = (g0, g1)
    return PairPrediction(pts3d, conf, desc, desc_conf, gaussians)


# ============================================================================================= options
def resolve_device(name: str) -> torch.device:
    """``"cpu"`` or ``"cuda"`` (the latter only when CUDA is usable).

    Raises:
        InputError: an unknown name, or CUDA requested where it is not available.
    """
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda":
        if not torch.cuda.is_available():
            build = "built without CUDA" if torch.version.cuda is None else "no CUDA device is visible"
            raise InputError(
                f"--device cuda: CUDA is not available (torch {torch.__version__}, {build}); use --device cpu"
            )
        return torch.device("cuda")
    raise InputError(f"--device {name!r}: use cpu or cuda")


def check_fusion_files(dino: Path | str | None, fusion: Path | str | None) -> None:
    """Semantic fusion needs both files (or neither, to skip it).

    Raises:
        InputError: one of the two is missing.
    """
    if (dino is None) != (fusion is None):
        given, other = ("--dino", "--fusion") if fusion is None else ("--fusion", "--dino")
        raise InputError(
            f"{given} needs {other} too: semantic fusion uses the DINOv3 encoder (--dino) and the trained fusion "
            "weights (--fusion); give both, or neither to skip the fusion"
        )
