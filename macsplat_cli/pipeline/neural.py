"""The neural backend: MASt3R (optionally with DINOv3 semantic fusion and a Splatt3R Gaussian head) in the stage slots.

The network runs **once per pair** (:meth:`NeuralBackend.predict`, cached on the content of the
two views); every stage reads that one prediction:

=============  ==========================================================================================
stage          what it does with the prediction
=============  ==========================================================================================
descriptors    the 24-d MASt3R descriptors (fused with DINOv3 features when ``--dino``/``--fusion`` are
               given), subsampled on a regular grid, with the descriptor confidence
matching       the shared :class:`~.run.FilteredMatcher` (reciprocal NN, ``c0·c1 > τ``), unchanged
pose           focal length of view 0 from its own point map (Weiszfeld), unless intrinsics were given;
               camera 1 from view 1's pixels and their 3-D points in camera 0 (PnP + RANSAC); metric
depth          z of each view's point map in its own camera frame; confidence from ``conf``
gaussians      the Splatt3R head's per-pixel Gaussians, or the classical surfels from that depth
=============  ==========================================================================================

**Pose: PnP, not Procrustes.** MASt3R gives view 1's points in camera 0's frame only; Procrustes
needs them in camera 1's frame too, i.e. a second forward pass with the views swapped. Measured on
ray-traced pairs (room and object scenes, 10°/30°/60° orbits, 10 000 points, 3 seeds; errors of
rotation / translation direction): with depth noise along view 1's own rays (2 %, 10 % outliers),
PnP is exact (0.000° / 0.000°; such errors do not move a point's projection) where Procrustes gives
0.01–0.03° / 0.05–0.35°; with 3 % scale disagreement between the two passes, PnP is unaffected and
Procrustes' translation direction is off by 2–20°. Procrustes only won under isotropic 3-D noise
(2 % of the depth in every axis: 0.3–0.5° / 0.1–2.7° against PnP's 0.4–1.1° / 0.5–8.6°), and it costs
a second pass of the network. So PnP (``cv2.solvePnPRansac``, SQPnP, then Levenberg–Marquardt on
the inliers), one pass.

**Descriptor sampling.** The shared matcher compares every descriptor of one view with every
descriptor of the other: a full 512×384 map (196 608 per view) is out of reach. Measured with
synthetic descriptors on a 20° room pair at 512×384 (2 CPU threads): a 4-px grid on both views
(12 288 each) took 1–3 s and gave 1 652 matches within 2 px of the truth; an 8-px grid 0.2 s and
135; top-k by confidence (12 288) 3 s and 1 212; an 8-px grid against the dense map of the other
view 13–23 s and 1 690; a 2-px grid 48 s and 14 119. The default is the 4-px grid
(:attr:`NeuralConfig.stride`). Grid matches sit on grid pixels, up to 2.8 px from the true ones:
:func:`refine_matches` then moves each view-1 pixel to the best descriptor of the dense map within
±2 px (22 ms), which took the 4-px grid's matches within 2 px from 1 652 to 1 786, 1 757 of them
within 1 px.

**Working size.** The photos are loaded by :func:`~.views.load_views`: long side ``--size`` (512,
MASt3R's training size), each side rounded to a multiple of 16 with K scaled per axis (MASt3R's own
loader crops to multiples of 16 instead; the aspect ratio changes by < 3 % here), RGB scaled to
[-1, 1] for the network. Both views must have the network's input size: view 0 goes in as loaded; a
view 1 of another size is scaled to cover view 0's size and centre-cropped (:class:`ViewWarp`,
intrinsics transformed accordingly); its outputs are sampled back onto its own pixels, and pixels
cropped away get no depth.

Symbols: ``H, W`` network input size (view 0's working size), ``D`` descriptor dimension (24).
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch

from ..cameras import rotmat_to_quat_np
from ..errors import InputError, ReconstructionError
from ..gaussians import quat_multiply
from ..neural.backbone import MASt3RBackbone
from ..neural.checkpoints import MAST3R_FILE, MAST3R_HF_REPO, CheckpointNotFoundError, load_mast3r, load_splatt3r
from ..neural.dinov3 import DINOv3Encoder, load_dinov3
from ..neural.fusion import ResidualSemanticFusion, fuse_descriptors, load_fusion
from ..neural.gaussian_head import GaussianHead, GaussianHeadOutput
from .matching import MatchConfig
from .pose import fundamental_from_pose, sampson_distance
from .run import DepthGaussians, FilteredMatcher, Pipeline, ReconstructConfig, Reconstruction, StageEvent, _jsonable
from .types import DepthMap, Features, Matches, PixelGaussians, TwoViewGeometry, View

__all__ = [
    "NeuralBackend",
    "NeuralConfig",
    "NeuralDepth",
    "NeuralDescriptors",
    "NeuralGaussians",
    "NeuralModels",
    "NeuralPipeline",
    "NeuralPose",
    "PairPrediction",
    "check_fusion_files",
    "ViewWarp",
    "estimate_focal_weiszfeld",
    "load_neural_models",
    "neural_reconstruct_config",
    "pose_from_pointmap",
    "refine_matches",
    "resolve_device",
    "sample_descriptors",
]

logger = logging.getLogger(__name__)

MISSING_WEIGHTS_HELP = (
    f"--backend neural needs the MASt3R checkpoint {MAST3R_FILE}: download it from {MAST3R_HF_REPO} "
    "(or the naver/mast3r README; licence CC BY-NC-SA 4.0, non-commercial) and pass --weights PATH, "
    "or pass a Splatt3R checkpoint with --gaussian-head (see models/mast3r.md)"
)


# ============================================================================================= configuration
@dataclass
class NeuralConfig:
    """Settings of the neural stages.

    Args:
        sampling: ``"grid"``: every ``stride``-th pixel of the descriptor map in both directions;
            ``"topk"``: the ``top_k`` pixels of highest descriptor confidence.
        stride: grid step in pixels of the network input (4 → 12 288 descriptors at 512×384).
        top_k: descriptors per view with ``sampling="topk"``.
        conf_threshold: point-map confidence (``conf ≥ 1``) a pixel needs to be used for the pose,
            the depth and the Gaussians (1.5: MASt3R's demo default for its exported cloud).
        focal_range: estimated focal lengths are clipped to this range times the 60° field-of-view
            prior (MASt3R's sparse alignment uses 0.5–3.5).
        weiszfeld_iters: reweighting iterations of the focal estimate.
        pnp_reproj_px: RANSAC inlier threshold of the PnP, in pixels at a 512-px long side (scaled
            with the working size); 5 px as DUSt3R's pair viewer and MASt3R's visloc.
        pnp_iters: RANSAC iterations.
        pnp_max_points: the PnP uses at most this many confident pixels (an even subsample).
        min_pose_points: fewer confident pixels than this in view 1 is a failure.
        verify_px: a match is verified when view 0's 3-D point at its pixel projects within this
            distance (pixels at a 512-px long side, at least 1.5 px) of its pixel in view 1, after
            :func:`refine_matches` moved that pixel to the best descriptor within the sampling cell.
        warn_inlier_ratio: below this PnP inlier ratio the pose is reported as doubtful.
        precision: ``"fp32"``, or ``"bf16"`` (autocast: matrix products in bfloat16, 1.8× faster on
            a CPU with AVX512-BF16 in ``benchmarks/bench_neural.py``; accuracy with the official
            weights unmeasured).
    """

    sampling: Literal["grid", "topk"] = "grid"
    stride: int = 4
    top_k: int = 12288
    conf_threshold: float = 1.5
    focal_range: tuple[float, float] = (0.5, 3.5)
    weiszfeld_iters: int = 10
    pnp_reproj_px: float = 5.0
    pnp_iters: int = 100
    pnp_max_points: int = 20000
    min_pose_points: int = 6
    verify_px: float = 5.0
    warn_inlier_ratio: float = 0.2
    precision: Literal["fp32", "bf16"] = "fp32"

    def __post_init__(self) -> None:
        if self.precision not in ("fp32", "bf16"):
            raise InputError(f"precision must be 'fp32' or 'bf16', got {self.precision!r}")
        if self.sampling not in ("grid", "topk"):
            raise InputError(f"descriptor sampling must be 'grid' or 'topk', got {self.sampling!r}")
        if self.stride < 1 or self.top_k < 1:
            raise InputError(f"stride ({self.stride}) and top_k ({self.top_k}) must be positive")


def neural_reconstruct_config(config: ReconstructConfig | None = None) -> ReconstructConfig:
    """``config`` (or the default) adapted to the neural stages.

    The SIFT fallback and the epipolar-guided re-matching are turned off (the pose does not come
    from the matches), and the matcher uses the learned confidence as is (``ratio_confidence=False``)
    with ``τ = 1`` on ``c0·c1`` (the descriptor confidence ``exp(x)``; MASt3R's visloc keeps pixels whose
    confidence exceeds 1.001).
    """
    c = dataclasses.replace(config) if config is not None else ReconstructConfig()
    c.fallback_descriptors = None
    c.guided_band_px = None
    c.matching = MatchConfig(conf_threshold=1.0, ratio_confidence=False, max_block_elems=c.matching.max_block_elems)
    return c


# ============================================================================================= models
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


@dataclass
class NeuralModels:
    """The loaded networks, in eval mode on ``device``.

    Attributes:
        backbone: MASt3R.
        gaussian_head: Splatt3R's Gaussian head, or None (classical surfels from the depth).
        dino: frozen DINOv3 encoder, or None (no semantic fusion).
        fusion: Residual Semantic Fusion, or None (no semantic fusion).
        device: where they run.
        files: the checkpoint of each role (``weights``, ``gaussian_head``, ``dino``, ``fusion``).
    """

    backbone: MASt3RBackbone
    gaussian_head: GaussianHead | None
    dino: DINOv3Encoder | None
    fusion: ResidualSemanticFusion | None
    device: torch.device
    files: dict[str, str] = field(default_factory=dict)

    @property
    def fusion_enabled(self) -> bool:
        return self.dino is not None and self.fusion is not None


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


def load_neural_models(
    *,
    weights: Path | str | None = None,
    gaussian_head: Path | str | None = None,
    dino: Path | str | None = None,
    fusion: Path | str | None = None,
    device: str = "cpu",
) -> NeuralModels:
    """Load the networks of the neural backend (all checks happen here, before any work).

    * ``weights`` (MASt3R ``.pth`` or Hugging Face folder): the backbone.
    * ``gaussian_head`` (Splatt3R ``.ckpt``): the Gaussian head. A Splatt3R checkpoint holds its
      frozen MASt3R too, so it alone is enough; with ``weights`` as well, the backbone comes from
      ``weights`` (its architecture, from its ``args``, also sizes the head) and only the head is taken
      from the Splatt3R file (Splatt3R trained its head on the released MASt3R weights, frozen).
    * ``dino`` and ``fusion`` go together: semantic fusion needs both the DINOv3 encoder and the
      trained fusion weights.

    Raises:
        CheckpointNotFoundError: neither ``weights`` nor ``gaussian_head`` (the message says which
            file is needed and where to get it), or a file that does not exist.
        CheckpointError / DINOv3CheckpointError / FusionCheckpointError: a file that does not fit.
        InputError: ``dino`` without ``fusion`` (or the reverse), widths that do not match, CUDA
            requested but unavailable.
    """
    dev = resolve_device(device)
    if weights is None and gaussian_head is None:
        raise CheckpointNotFoundError(MISSING_WEIGHTS_HELP)
    check_fusion_files(dino, fusion)
    files: dict[str, str] = {}
    head: GaussianHead | None = None
    if weights is not None:
        backbone, _ = load_mast3r(weights)
        files["weights"] = str(weights)
        if gaussian_head is not None:
            head_cfg = backbone.config.replace(head_type="gaussian_head")
            _, head, _ = load_splatt3r(gaussian_head, backbone_config=head_cfg)
            files["gaussian_head"] = str(gaussian_head)
    else:
        assert gaussian_head is not None
        backbone, head, _ = load_splatt3r(gaussian_head)
        files["weights"] = files["gaussian_head"] = str(gaussian_head)
    encoder = fusion_module = None
    if dino is not None and fusion is not None:
        encoder = load_dinov3(dino, device=dev)
        fusion_module = load_fusion(fusion, device=dev)
        if encoder.config.embed_dim != fusion_module.config.dino_dim:
            raise InputError(
                f"{fusion}: the fusion weights expect {fusion_module.config.dino_dim}-d DINOv3 features, but {dino} "
                f"is DINOv3 {encoder.config.name} ({encoder.config.embed_dim}-d)"
            )
        if fusion_module.config.desc_dim != backbone.config.local_feat_dim:
            raise InputError(
                f"{fusion}: the fusion weights are for {fusion_module.config.desc_dim}-d descriptors, the backbone "
                f"predicts {backbone.config.local_feat_dim}-d ones"
            )
        files["dino"], files["fusion"] = str(dino), str(fusion)
    backbone = backbone.to(dev).eval()
    if head is not None:
        head = head.to(dev).eval()
    logger.info(
        "neural backend on %s: MASt3R %.0fM parameters%s%s",
        dev,
        sum(p.numel() for p in backbone.parameters()) / 1e6,
        ", Splatt3R Gaussian head" if head is not None else "",
        f", DINOv3 {encoder.config.name} fusion" if encoder is not None else "",
    )
    return NeuralModels(backbone, head, encoder, fusion_module, dev, files)


# ============================================================================================= view ↔ network grid
@dataclass(frozen=True)
class ViewWarp:
    """Maps a view's working pixels onto the network input grid: ``u = x·sx − ox``, ``v = y·sy − oy``.

    Pixel centres at +0.5 on both grids (exact for per-axis scaling and integer crops).

    Attributes:
        view_size: (W, H) of the view.
        net_size: (W, H) of the network input.
        scale: (sx, sy).
        offset: (ox, oy), the crop's top-left corner in the scaled image.
    """

    view_size: tuple[int, int]
    net_size: tuple[int, int]
    scale: tuple[float, float] = (1.0, 1.0)
    offset: tuple[int, int] = (0, 0)

    @classmethod
    def fit(cls, view_size: tuple[int, int], net_size: tuple[int, int]) -> ViewWarp:
        """Scale the view to cover ``net_size`` (aspect kept up to rounding), then centre-crop."""
        (w, h), (wn, hn) = view_size, net_size
        if (w, h) == (wn, hn):
            return cls(view_size, net_size)
        s = max(wn / w, hn / h)
        wr, hr = max(wn, round(w * s)), max(hn, round(h * s))
        return cls(view_size, net_size, (wr / w, hr / h), ((wr - wn) // 2, (hr - hn) // 2))

    @property
    def identity(self) -> bool:
        return self.view_size == self.net_size

    def to_net(self, xy: np.ndarray) -> np.ndarray:
        """View pixels → network pixels. [N, 2] → [N, 2]"""
        return xy * np.asarray(self.scale) - np.asarray(self.offset, np.float64)

    def from_net(self, uv: np.ndarray) -> np.ndarray:
        """Network pixels → view pixels. [N, 2] → [N, 2]"""
        return (uv + np.asarray(self.offset, np.float64)) / np.asarray(self.scale)

    def K_net(self, K: np.ndarray) -> np.ndarray:
        """The view's intrinsics on the network grid. [3, 3]"""
        out = np.array(K, dtype=np.float64)
        out[0] *= self.scale[0]
        out[1] *= self.scale[1]
        out[0, 2] -= self.offset[0]
        out[1, 2] -= self.offset[1]
        return out

    def image(self, img: np.ndarray) -> np.ndarray:
        """The view's image (or mask) resampled onto the network grid. [H, W, ...] → [Hn, Wn, ...]"""
        if self.identity:
            return img
        (w, h), (wn, hn) = self.view_size, self.net_size
        wr, hr = round(w * self.scale[0]), round(h * self.scale[1])
        if img.dtype == bool:
            r = cv2.resize(img.astype(np.uint8), (wr, hr), interpolation=cv2.INTER_NEAREST).astype(bool)
        else:
            r = cv2.resize(img, (wr, hr), interpolation=cv2.INTER_AREA if wr < w else cv2.INTER_CUBIC)
            r = np.clip(r, 0.0, 1.0)
        ox, oy = self.offset
        return np.ascontiguousarray(r[oy : oy + hn, ox : ox + wn])

    def sample(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A network-grid map read back at the view's pixels (nearest neighbour).

        Returns the map on the view's grid and the pixels that fall inside the network input.
        [Hn, Wn, ...] → ([H, W, ...], [H, W] bool)
        """
        (w, h), (wn, hn) = self.view_size, self.net_size
        if self.identity:
            return a, np.ones((h, w), bool)
        u = np.floor((np.arange(w) + 0.5) * self.scale[0] - self.offset[0]).astype(np.int64)
        v = np.floor((np.arange(h) + 0.5) * self.scale[1] - self.offset[1]).astype(np.int64)
        inside = ((v >= 0) & (v < hn))[:, None] & ((u >= 0) & (u < wn))[None, :]
        out = a[np.clip(v, 0, hn - 1)[:, None], np.clip(u, 0, wn - 1)[None, :]]
        return out, inside


# ============================================================================================= geometry
def estimate_focal_weiszfeld(
    pts: np.ndarray,  # [H, W, 3]
    pp: tuple[float, float] | None = None,
    *,
    mask: np.ndarray | None = None,  # [H, W]
    iters: int = 10,
    focal_base: float | None = None,
    focal_range: tuple[float, float] = (0.5, 3.5),
) -> float:
    """Focal length (pixels, square pixels) of the camera that sees the point map ``pts`` in its own frame.

    With ``p = (x/z, y/z)`` and ``d`` the pixel's offset from the principal point, ``f`` minimises
    ``Σ |d − f·p|`` (a robust L1 fit): start from the least-squares ``f = Σ p·d / Σ |p|²``, then
    ``iters`` Weiszfeld reweightings ``w = 1/max(|d − f·p|, 1e-8)``. Pixel centres at +0.5.

    Args:
        pts: point map in the camera's frame. [H, W, 3]
        pp: principal point (default: the image centre).
        mask: pixels to use (default: all with finite points in front of the camera). [H, W]
        iters: reweighting iterations.
        focal_base: with ``focal_range``, the result is clipped to ``[lo, hi] × focal_base``
            (default base: a 60° field of view across the long side).

    Raises:
        ReconstructionError: no usable pixel.
    """
    h, w = pts.shape[:2]
    cx, cy = pp if pp is not None else (w / 2.0, h / 2.0)
    base = focal_base if focal_base is not None else max(w, h) / (2.0 * math.tan(math.radians(30.0)))
    ys, xs = np.mgrid[0:h, 0:w]
    d = np.stack([xs + 0.5 - cx, ys + 0.5 - cy], -1).reshape(-1, 2)
    P = pts.reshape(-1, 3).astype(np.float64)
    ok = np.isfinite(P).all(1) & (P[:, 2] > 1e-12)
    if mask is not None:
        ok &= mask.reshape(-1)
    if not ok.any():
        raise ReconstructionError("focal length: no pixel of the point map is in front of the camera")
    p = P[ok, :2] / P[ok, 2:3]
    d = d[ok]
    den = float((p * p).sum())
    f = float((p * d).sum()) / den if den > 0 else base
    for _ in range(iters):
        wgt = 1.0 / np.maximum(np.linalg.norm(d - f * p, axis=1), 1e-8)
        den = float((wgt[:, None] * p * p).sum())
        if den <= 0:
            break
        f = float((wgt[:, None] * p * d).sum()) / den
    lo, hi = focal_range[0] * base, focal_range[1] * base
    return float(np.clip(f if np.isfinite(f) else base, lo, hi))


@dataclass
class PnPResult:
    """Pose of a camera from 2-D ↔ 3-D correspondences: ``x_cam = R·X + t``.

    Attributes:
        R: rotation. [3, 3]
        t: translation, in the points' units. [3]
        inliers: the RANSAC inliers. [N] bool
        median_error_px: median reprojection error of the inliers after refinement.
    """

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    median_error_px: float


def pose_from_pointmap(
    xy: np.ndarray,  # [N, 2]
    X: np.ndarray,  # [N, 3]
    K: np.ndarray,  # [3, 3]
    *,
    threshold_px: float = 5.0,
    iterations: int = 100,
    confidence: float = 0.999,
    min_points: int = 6,
) -> PnPResult:
    """The pose of the camera that sees the 3-D points ``X`` at pixels ``xy`` (PnP + RANSAC).

    For MASt3R: ``X`` = view 1's point map (expressed in camera 0's frame), ``xy`` = those pixels of
    view 1, ``K`` = view 1's intrinsics; the result is the relative pose ``X_cam1 = R·X_cam0 + t``.
    SQPnP inside RANSAC, then Levenberg–Marquardt on the inliers. Pixel centres at +0.5 (OpenCV's
    projection has none: a constant shift of both the pixels and the principal point, so no effect).

    Raises:
        ReconstructionError: fewer than ``min_points`` points, or no pose found.
    """
    ok = np.isfinite(X).all(1) & np.isfinite(xy).all(1)
    X, xy = np.ascontiguousarray(X[ok], np.float64), np.ascontiguousarray(xy[ok], np.float64)
    n = len(X)
    if n < max(min_points, 4):
        raise ReconstructionError(
            f"pose could not be estimated: the network is confident about only {n} pixels of the second view"
        )
    K = np.asarray(K, np.float64)
    found, rvec, tvec, idx = False, None, None, None
    # SQPnP is the most accurate minimal solver, but OpenCV asserts on degenerate samples (e.g. nearly
    # coincident points); EPnP is the fallback.
    for method in (cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP):
        try:
            found, rvec, tvec, idx = cv2.solvePnPRansac(
                X, xy, K, None, iterationsCount=iterations, reprojectionError=threshold_px, confidence=confidence,
                flags=method,
            )  # fmt: skip
        except cv2.error as e:
            logger.debug("PnP (method %d) failed: %s", method, str(e).strip().splitlines()[-1])
            continue
        if found:
            break
    if (
        not found
        or idx is None
        or len(idx) < 4
        or rvec is None
        or not (np.isfinite(rvec).all() and np.isfinite(tvec).all())
    ):
        raise ReconstructionError(
            f"pose could not be estimated: no camera pose explains the network's point map of the second view "
            f"({n} confident pixels)"
        )
    inliers = np.zeros(n, bool)
    inliers[idx.reshape(-1)] = True
    try:
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], xy[inliers], K, None, rvec, tvec)
    except cv2.error as e:  # keep the RANSAC pose
        logger.debug("PnP refinement failed: %s", str(e).strip().splitlines()[-1])
    proj = cv2.projectPoints(X, rvec, tvec, K, None)[0].reshape(-1, 2)
    err = np.linalg.norm(proj - xy, axis=1)
    inliers = err < threshold_px  # re-classified after the refinement
    full = np.zeros(len(ok), bool)
    full[np.flatnonzero(ok)[inliers]] = True
    R = cv2.Rodrigues(rvec)[0]
    median = float(np.median(err[inliers])) if inliers.any() else float("nan")
    return PnPResult(R=R, t=tvec.reshape(3).astype(np.float64), inliers=full, median_error_px=median)


def sample_descriptors(
    conf: np.ndarray,  # [H, W]
    *,
    sampling: Literal["grid", "topk"] = "grid",
    stride: int = 4,
    top_k: int = 12288,
    mask: np.ndarray | None = None,  # [H, W]
) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Which pixels of a dense descriptor map to match: flat row-major indices, and the grid shape.

    ``grid``: pixels ``(stride//2 + i·stride, stride//2 + j·stride)``, (rows, cols) returned when no
    pixel was masked out; ``topk``: the ``top_k`` most confident pixels (ties broken by position).

    Returns:
        ``(indices [M] int64, grid or None)``.
    """
    h, w = conf.shape
    if sampling == "grid":
        rows = np.arange(stride // 2, h, stride)
        cols = np.arange(stride // 2, w, stride)
        idx = (rows[:, None] * w + cols[None, :]).reshape(-1)
        grid: tuple[int, int] | None = (len(rows), len(cols))
    elif sampling == "topk":
        flat = conf.reshape(-1)
        k = min(top_k, flat.size)
        idx = np.sort(np.argsort(-flat, kind="stable")[:k])
        grid = None
    else:
        raise InputError(f"descriptor sampling must be 'grid' or 'topk', got {sampling!r}")
    if mask is not None:
        keep = mask.reshape(-1)[idx]
        if not keep.all():
            idx, grid = idx[keep], None
    return idx.astype(np.int64), grid


def refine_matches(pred: PairPrediction, matches: Matches, radius: int) -> Matches:
    """Move each match's view-1 pixel to the best descriptor within ``radius`` pixels on the dense map.

    Grid-sampled descriptors only match grid pixels, up to ``stride/√2`` px from the true one; the
    dense map of view 1 is available, so each match is snapped to the pixel of the ``(2r+1)²`` window
    around it whose descriptor is most similar to view 0's (cosine). Confidences and indices are kept.
    """
    if radius <= 0 or len(matches) == 0:
        return matches
    wn, hn = pred.net_size
    uv0 = pred.warps[0].to_net(matches.xy0)
    uv1 = pred.warps[1].to_net(matches.xy1)
    i0 = np.clip(np.floor(uv0[:, 1]).astype(np.int64), 0, hn - 1)
    j0 = np.clip(np.floor(uv0[:, 0]).astype(np.int64), 0, wn - 1)
    i1 = np.floor(uv1[:, 1]).astype(np.int64)
    j1 = np.floor(uv1[:, 0]).astype(np.int64)
    d0 = pred.desc[0][i0, j0]  # [M, D]
    offsets = np.arange(-radius, radius + 1)
    di, dj = (a.reshape(-1) for a in np.meshgrid(offsets, offsets, indexing="ij"))  # [K]
    ii, jj = i1[:, None] + di[None], j1[:, None] + dj[None]  # [M, K]
    inside = (ii >= 0) & (ii < hn) & (jj >= 0) & (jj < wn)
    cand = pred.desc[1][np.clip(ii, 0, hn - 1), np.clip(jj, 0, wn - 1)]  # [M, K, D]
    sim = np.einsum("mkd,md->mk", cand, d0) / np.maximum(
        np.linalg.norm(cand, axis=-1) * np.linalg.norm(d0, axis=-1, keepdims=True), 1e-12
    )
    sim = np.where(inside & pred.mask[1][np.clip(ii, 0, hn - 1), np.clip(jj, 0, wn - 1)], sim, -np.inf)
    best = np.argmax(sim, axis=1)
    rows = np.arange(len(best))
    uv1_new = np.stack([jj[rows, best] + 0.5, ii[rows, best] + 0.5], 1).astype(np.float64)
    xy1 = pred.warps[1].from_net(uv1_new)
    return Matches(matches.xy0, xy1, matches.conf, matches.idx0, matches.idx1, dict(matches.counts))


def _rotation_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _pixel_grid(h: int, w: int) -> np.ndarray:
    """Pixel centres (+0.5) of an h×w grid, row-major. [h·w, 2]"""
    ys, xs = np.mgrid[0:h, 0:w]
    return np.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], 1).astype(np.float64)


def _scale_of_512(w: int, h: int) -> float:
    return max(w, h) / 512.0


# ============================================================================================= the prediction
@dataclass
class PairPrediction:
    """One forward pass on a pair, on the network grid, moved to the CPU.

    Attributes:
        net_size: (W, H) of the network input (view 0's working size).
        pts3d: both views' point maps in **camera 0's** frame (metres for the metric checkpoint). [2, H, W, 3]
        conf: point-map confidences (≥ 1). [2, H, W]
        desc: descriptors, fused with DINOv3 features when the fusion ran. [2, H, W, D]
        desc_conf: descriptor confidences with the activation's floor removed (``exp(x)`` ≥ 0, whether
            the backbone was built as MASt3R's checkpoint (``exp``) or as Splatt3R does (``1 + exp``)). [2, H, W]
        mask: pixels of each view inside the image's alpha mask, on the network grid. [2, H, W] bool
        warps: view ↔ network grid of each view (identity for view 0).
        gaussians: the head's Gaussians of both views (camera-0 frame, batch of 1), or None.
        fusion_applied: whether semantic fusion changed the descriptors.
        fusion_report: what the fusion step did (one line).
        seconds: wall time of the forward pass (backbone, fusion, head).
    """

    net_size: tuple[int, int]
    pts3d: np.ndarray
    conf: np.ndarray
    desc: np.ndarray
    desc_conf: np.ndarray
    mask: np.ndarray
    warps: tuple[ViewWarp, ViewWarp]
    gaussians: tuple[GaussianHeadOutput, GaussianHeadOutput] | None
    fusion_applied: bool
    fusion_report: str
    seconds: float


def _view_key(v: View) -> tuple:
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(v.image).tobytes())
    h.update(np.ascontiguousarray(v.mask).tobytes())
    return (v.name, v.image.shape, h.hexdigest())


class NeuralBackend:
    """The networks and the per-pair cache the neural stages share.

    :meth:`predict` runs the network once per pair of views (keyed on the views' names and pixel
    content, the last ``cache_size`` pairs kept) and :meth:`stages` gives the pipeline's stage callables.

    Args:
        models: the loaded networks (:func:`load_neural_models`), or any object with the same attributes
            (tests use a stand-in backbone that returns known point maps).
        config: neural stage settings.
        cache_size: pairs kept in the cache.
    """

    def __init__(self, models: NeuralModels, config: NeuralConfig | None = None, *, cache_size: int = 2) -> None:
        self.models = models
        self.config = config or NeuralConfig()
        self.cache_size = cache_size
        self._cache: collections.OrderedDict[tuple, PairPrediction] = collections.OrderedDict()
        self.forward_calls = 0
        self.last: PairPrediction | None = None

    # ------------------------------------------------------------------ network
    def predict(self, v0: View, v1: View) -> PairPrediction:
        """The network's outputs for the pair (cached)."""
        key = (_view_key(v0), _view_key(v1))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            self.last = hit
            return hit
        pred = self._forward(v0, v1)
        self._cache[key] = pred
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        self.last = pred
        return pred

    def _forward(self, v0: View, v1: View) -> PairPrediction:
        m = self.models
        dev = m.device
        net_size = (v0.width, v0.height)
        warps = (ViewWarp(net_size, net_size), ViewWarp.fit((v1.width, v1.height), net_size))
        if not warps[1].identity:
            logger.info(
                "%s is %dx%d, %s %dx%d: resized and centre-cropped to %dx%d for the network",
                v1.name, v1.width, v1.height, v0.name, v0.width, v0.height, *net_size,
            )  # fmt: skip
        rgb = np.stack([w.image(v.image) for w, v in zip(warps, (v0, v1))])  # [2, H, W, 3] in [0, 1]
        mask = np.stack([w.image(v.mask) for w, v in zip(warps, (v0, v1))])
        img = torch.from_numpy(np.ascontiguousarray(rgb, np.float32)).permute(0, 3, 1, 2).to(dev) * 2.0 - 1.0
        t0 = time.perf_counter()
        bf16 = self.config.precision == "bf16"
        with torch.no_grad(), torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16):
            out1, out2 = m.backbone(img[:1], img[1:])
            desc = torch.cat([out1.desc, out2.desc])  # [2, H, W, D]
            fused = fuse_descriptors(desc, img, fusion=m.fusion, encoder=m.dino)
            gaussians = None
            if m.gaussian_head is not None:
                g1, g2 = m.gaussian_head(out1, out2, (img[:1] + 1) / 2, (img[1:] + 1) / 2)
                gaussians = tuple(
                    GaussianHeadOutput(**{f.name: getattr(g, f.name).float().cpu() for f in dataclasses.fields(g)})
                    for g in (g1, g2)
                )
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
        seconds = time.perf_counter() - t0
        self.forward_calls += 1
        vmin = float(m.backbone.config.desc_conf_mode[1])

        def cpu(*ts: torch.Tensor) -> np.ndarray:
            return torch.cat([t.float() for t in ts]).cpu().numpy()

        pred = PairPrediction(
            net_size=net_size,
            pts3d=cpu(out1.pts3d, out2.pts3d),
            conf=cpu(out1.conf, out2.conf),
            desc=fused.desc.float().cpu().numpy(),
            desc_conf=np.maximum(cpu(out1.desc_conf, out2.desc_conf) - vmin, 0.0),
            mask=mask,
            warps=warps,
            gaussians=gaussians,  # type: ignore[arg-type]
            fusion_applied=fused.applied,
            fusion_report=fused.report,
            seconds=seconds,
        )
        logger.info("network forward pass on %s at %dx%d: %.2f s", dev, *net_size, seconds)
        return pred

    # ------------------------------------------------------------------ stages and report
    def stages(self, config: ReconstructConfig) -> dict[str, Any]:
        """The stage callables for :class:`~.run.Pipeline` (keyword arguments of its constructor)."""
        gaussians = NeuralGaussians(self) if self.models.gaussian_head is not None else DepthGaussians(config.gaussians)
        return {
            "descriptors": NeuralDescriptors(self),
            "matcher": FilteredMatcher(config.matching),
            "pose": NeuralPose(self),
            "depth": NeuralDepth(self),
            "gaussians": gaussians,
        }

    def network_name(self) -> str:
        c = self.models.backbone.config
        return f"mast3r (enc {c.enc_embed_dim}x{c.enc_depth}, dec {c.dec_embed_dim}x{c.dec_depth})"

    def fusion_name(self) -> str:
        if not self.models.fusion_enabled:
            return "skipped (no --dino/--fusion weights)"
        assert self.models.dino is not None
        return f"dinov3-{self.models.dino.config.name}+residual-semantic-fusion"

    def report(self) -> dict[str, Any]:
        """The ``neural`` section of the run report."""
        last = self.last
        return {
            "device": str(self.models.device),
            "network": self.network_name(),
            "files": dict(self.models.files),
            "network_size": list(last.net_size) if last is not None else None,
            "forward_s": last.seconds if last is not None else None,
            "forward_calls": self.forward_calls,
            "fusion": {
                "applied": bool(last.fusion_applied) if last is not None else False,
                "detail": last.fusion_report if last is not None else self.fusion_name(),
            },
            "gaussian_head": self.models.gaussian_head is not None,
            "config": dataclasses.asdict(self.config),
        }


# ============================================================================================= stages
class NeuralDescriptors:
    """Descriptor stage: the network's (fused) dense descriptors, subsampled, with their confidence.

    The network needs both views: the pipeline calls :meth:`describe_pair`, so the forward pass
    is timed as this stage.
    """

    def __init__(self, backend: NeuralBackend) -> None:
        self.backend = backend
        fusion = "+" + backend.fusion_name() if backend.models.fusion_enabled else " (semantic fusion skipped)"
        self.name = f"neural:mast3r-desc{backend.models.backbone.config.local_feat_dim}{fusion}"

    def features(self, pred: PairPrediction, k: int) -> Features:
        """View ``k``'s sampled descriptors, pixel coordinates in the view's working grid."""
        cfg = self.backend.config
        wn, hn = pred.net_size
        idx, grid = sample_descriptors(
            pred.desc_conf[k], sampling=cfg.sampling, stride=cfg.stride, top_k=cfg.top_k, mask=pred.mask[k]
        )
        uv = np.stack([idx % wn + 0.5, idx // wn + 0.5], 1).astype(np.float64)
        d = pred.desc[k].reshape(hn * wn, -1)[idx]
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return Features(
            xy=pred.warps[k].from_net(uv),
            desc=np.ascontiguousarray(d, np.float32),
            conf=np.ascontiguousarray(pred.desc_conf[k].reshape(-1)[idx], np.float32),
            grid=grid,
        )

    def describe_pair(self, v0: View, v1: View) -> list[Features]:
        pred = self.backend.predict(v0, v1)
        return [self.features(pred, 0), self.features(pred, 1)]

    def __call__(self, view: View) -> Features:
        raise TypeError("the neural descriptors need both views: call describe_pair(v0, v1)")


class NeuralPose:
    """Pose stage: focal by Weiszfeld (unknown intrinsics), camera 1 by PnP on the network's point map; metric."""

    name = "neural:mast3r-pointmap-pnp"

    def __init__(self, backend: NeuralBackend) -> None:
        self.backend = backend

    def __call__(self, v0: View, v1: View, matches: Matches) -> TwoViewGeometry:
        cfg = self.backend.config
        pred = self.backend.predict(v0, v1)
        wn, hn = pred.net_size
        px = _scale_of_512(wn, hn)
        ok = (pred.conf > cfg.conf_threshold) & pred.mask & (np.isfinite(pred.pts3d).all(-1))  # [2, H, W]
        info: dict[str, float | int | str | bool] = {}
        K0, K1 = v0.K.copy(), v1.K.copy()
        estimated = False
        if v0.intrinsics_source == "prior":
            f0 = estimate_focal_weiszfeld(
                pred.pts3d[0], (K0[0, 2], K0[1, 2]), mask=ok[0], iters=cfg.weiszfeld_iters,
                focal_base=float(K0[0, 0]), focal_range=cfg.focal_range,
            )  # fmt: skip
            info["focal_prior_px"] = float(K0[0, 0])
            K0[0, 0] = K0[1, 1] = f0
            estimated = True
        if v1.intrinsics_source == "prior":
            # View 1's own-frame point map needs a second pass; assume view 0's field of view (one camera).
            f1 = float(K0[0, 0]) * max(v1.width, v1.height) / max(v0.width, v0.height)
            K1[0, 0] = K1[1, 1] = f1
            estimated = True
        info["focal_estimated"] = estimated

        K1n = pred.warps[1].K_net(K1)
        sel = np.flatnonzero(ok[1].reshape(-1))
        if len(sel) > cfg.pnp_max_points:
            sel = sel[np.linspace(0, len(sel) - 1, cfg.pnp_max_points).astype(np.int64)]
        uv1 = _pixel_grid(hn, wn)[sel]
        X1 = pred.pts3d[1].reshape(-1, 3)[sel].astype(np.float64)
        pnp = pose_from_pointmap(
            uv1, X1, K1n, threshold_px=cfg.pnp_reproj_px * px, iterations=cfg.pnp_iters,
            min_points=cfg.min_pose_points,
        )  # fmt: skip
        R, t = pnp.R, pnp.t
        n_in = int(pnp.inliers.sum())
        ratio = n_in / max(len(sel), 1)
        if ratio < cfg.warn_inlier_ratio:
            logger.warning(
                "the network's point maps are not consistent with one camera pose: only %d of %d confident pixels "
                "(%.0f %%) agree with the PnP pose",
                n_in, len(sel), 100 * ratio,
            )  # fmt: skip
        # parallax over view 0's confident points
        X0 = pred.pts3d[0][ok[0]].astype(np.float64)
        c1 = -R.T @ t
        if len(X0):
            a, b = X0, X0 - c1
            cos = np.sum(a * b, 1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
            parallax = float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))
        else:
            parallax = float("nan")
        radius = cfg.stride // 2 if cfg.sampling == "grid" else 1
        matches = refine_matches(pred, matches, radius)
        verified = self._verify(pred, ok[0], matches, R, t, K1, max(cfg.verify_px * px, 1.5))
        inl = matches.subset(verified, "verified")
        if len(inl):
            F = fundamental_from_pose(R, t, K0, K1)
            sampson = float(np.median(np.abs(sampson_distance(F, inl.xy0, inl.xy1))))
        else:
            sampson = float("nan")
        info.update(
            method="pnp-ransac",
            pnp_points=len(sel),
            pnp_inliers=n_in,
            inlier_ratio=ratio,
            pnp_median_reprojection_px=pnp.median_error_px,
            inliers=len(inl),
            median_sampson_px=sampson,
            median_parallax_deg=parallax,
            rotation_deg=_rotation_deg(R),
            translation_norm=float(np.linalg.norm(t)),
            scale="metric",
        )
        logger.debug("neural pose: %s", info)
        return TwoViewGeometry(R=R, t=t, K0=K0, K1=K1, inliers=inl, info=info)

    @staticmethod
    def _verify(
        pred: PairPrediction, ok0: np.ndarray, matches: Matches, R: np.ndarray, t: np.ndarray, K1: np.ndarray,
        tol_px: float,
    ) -> np.ndarray:  # fmt: skip
        """Matches whose view-0 3-D point projects within ``tol_px`` of their view-1 pixel. [M] bool"""
        if len(matches) == 0:
            return np.zeros(0, bool)
        wn, hn = pred.net_size
        uv0 = pred.warps[0].to_net(matches.xy0)
        i = np.clip(np.floor(uv0[:, 1]).astype(np.int64), 0, hn - 1)
        j = np.clip(np.floor(uv0[:, 0]).astype(np.int64), 0, wn - 1)
        X = pred.pts3d[0][i, j].astype(np.float64) @ R.T + t
        with np.errstate(divide="ignore", invalid="ignore"):
            p = X @ np.asarray(K1, np.float64).T
            uv = p[:, :2] / p[:, 2:3]
        err = np.linalg.norm(uv - matches.xy1, axis=1)
        return ok0[i, j] & (X[:, 2] > 0) & np.isfinite(err) & (err < tol_px)


def _depth_confidence(conf: np.ndarray) -> np.ndarray:
    """MASt3R's ``conf ≥ 1`` → [0, 1): ``1 − 1/conf``."""
    return np.clip(1.0 - 1.0 / np.maximum(conf, 1e-12), 0.0, 1.0).astype(np.float32)


class NeuralDepth:
    """Depth stage: each view's point map in its own camera frame, its z; confidence ``1 − 1/conf``."""

    name = "neural:mast3r-pointmap"

    def __init__(self, backend: NeuralBackend) -> None:
        self.backend = backend

    def __call__(self, views: list[View], geometry: TwoViewGeometry) -> list[DepthMap]:
        cfg = self.backend.config
        pred = self.backend.predict(views[0], views[1])
        out = []
        for k, v in enumerate(views):
            X = pred.pts3d[k].astype(np.float64)
            if k == 1:
                X = X @ geometry.R.T + geometry.t
            z = X[..., 2].astype(np.float32)
            good = (pred.conf[k] > cfg.conf_threshold) & pred.mask[k] & np.isfinite(z) & (z > 0)
            conf = np.where(good, _depth_confidence(pred.conf[k]), 0.0).astype(np.float32)
            z = np.where(good, z, 0.0).astype(np.float32)
            z_v, inside = pred.warps[k].sample(z)
            c_v, _ = pred.warps[k].sample(conf)
            keep = inside & v.mask
            out.append(
                DepthMap(
                    depth=np.ascontiguousarray(np.where(keep, z_v, 0.0), np.float32),
                    confidence=np.ascontiguousarray(np.where(keep, c_v, 0.0), np.float32),
                )
            )
        if not any(d.valid.any() for d in out):
            raise ReconstructionError(
                f"no depth: the network's confidence is below {cfg.conf_threshold} (or its points are behind the "
                "cameras) at every pixel"
            )
        return out


class NeuralGaussians:
    """Gaussian stage: the Splatt3R head's per-pixel Gaussians, moved into each view's camera frame.

    The head predicts both views' Gaussians in camera 0's frame; view 1's means and rotations are
    transformed with the estimated pose. SH coefficients are kept as predicted: they are world-frame
    (camera 0) quantities, which is what :meth:`PixelGaussians.to_world` assumes. Pixels with a depth
    (confident, in front of the camera, inside the alpha mask) carry a Gaussian.
    """

    name = "neural:splatt3r-gaussian-head"

    def __init__(self, backend: NeuralBackend) -> None:
        self.backend = backend

    def __call__(self, views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap]) -> list[PixelGaussians]:
        pred = self.backend.predict(views[0], views[1])
        assert pred.gaussians is not None, "NeuralGaussians needs the Gaussian head"
        out = []
        for k, (g, v, d) in enumerate(zip(pred.gaussians, views, depths)):
            means = g.means[0].double()
            quats = g.quats_wxyz[0].double()
            if k == 1:
                R = torch.from_numpy(geometry.R)
                means = means @ R.T + torch.from_numpy(geometry.t)
                q = torch.from_numpy(rotmat_to_quat_np(geometry.R))
                quats = quat_multiply(q.expand_as(quats), quats)
            maps = {
                "means": means.float(),
                "log_scales": g.log_scales[0],
                "quats": quats.float(),
                "opacity_logits": g.opacity_logits[0][..., None],
                "sh": g.sh_band_major[0].reshape(*means.shape[:2], -1),
            }
            warp = pred.warps[k]
            on_view = {n: torch.from_numpy(np.ascontiguousarray(warp.sample(a.numpy())[0])) for n, a in maps.items()}
            h, w = v.height, v.width
            out.append(
                PixelGaussians(
                    means=on_view["means"],
                    log_scales=on_view["log_scales"],
                    quats=on_view["quats"],
                    opacity_logits=on_view["opacity_logits"][..., 0],
                    sh=on_view["sh"].reshape(h, w, -1, 3),
                    valid=torch.from_numpy(np.ascontiguousarray(d.valid)),
                    cam_to_world=torch.from_numpy(geometry.cam_to_world(k)),
                )
            )
        return out


# ============================================================================================= the pipeline
class NeuralPipeline(Pipeline):
    """:class:`~.run.Pipeline` with the neural stages; the reconstruction is metric.

    Args:
        backend: the networks and their per-pair cache.
        config: pipeline settings; default :func:`neural_reconstruct_config` (start from it to keep the
            neural matching defaults). The SIFT fallback and guided matching are always off.
    """

    def __init__(self, backend: NeuralBackend, config: ReconstructConfig | None = None) -> None:
        cfg = neural_reconstruct_config() if config is None else dataclasses.replace(config)
        cfg.fallback_descriptors = None  # the pose does not come from the matches: no SIFT retry ...
        cfg.guided_band_px = None  # ... and no epipolar-guided re-matching
        self.backend = backend
        super().__init__(cfg, **backend.stages(cfg))

    def backends(self) -> dict[str, str]:
        names = super().backends()
        names["network"] = f"{self.backend.network_name()} on {self.backend.models.device}"
        names["fusion"] = self.backend.fusion_name()
        return names

    def run(self, paths: Sequence[str | Path], *, on_stage: StageEvent | None = None) -> Reconstruction:
        """As :meth:`Pipeline.run`; the result has ``scale="metric"`` and a ``neural`` report section.

        Raises:
            InputError: unreadable photos or intrinsics.
            ReconstructionError: the network's outputs give no pose or no confident depth.
        """
        rec = super().run(paths, on_stage=on_stage)
        rec.scale = "metric"
        rec.report = _jsonable({**rec.report, "scale": "metric", "neural": self.backend.report()})
        return rec
