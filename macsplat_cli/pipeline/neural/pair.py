"""The neural backend's ``pair`` stage: both views through the network once (:class:`NeuralPair`), and the
settings of every neural stage (:class:`NeuralConfig`).

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

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from ...errors import InputError
from ...gaussians import GaussianMaps
from ...neural.predictor import PairPredictor, prediction_from_outputs, resolve_device
from ...report import FusionReport, NeuralReport
from ..types import View
from .warp import ViewWarp

__all__ = ["NetworkPair", "NeuralConfig", "NeuralPair"]

logger = logging.getLogger(__name__)


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
        min_pnp_inlier_ratio: below this share of the confident pixels agreeing with the PnP pose, the network's
            point maps are not one rigid scene seen by two cameras: the pose is doubted (``info["doubts"]``; refused
            unless ``--accept-low-confidence``, as every doubt of :func:`~..pose_confidence.accept_pose`).
        precision: ``"fp32"``, or ``"bf16"`` (autocast: matrix products in bfloat16; measured:
            benchmarks/history/neural.md).
        fusion: ``"always"``: the semantic fusion (DINOv3 + fusion MLP) runs with the network pass;
            ``"auto"``: it is skipped while the backbone's own descriptors verify enough matches
            (:attr:`~..pose.PoseSearchConfig.fallback_min_inliers`), and runs on demand otherwise, as the
            descriptor fallback. Only with DINOv3/fusion weights and a torch predictor (an ONNX file has the
            fusion inside its graph).
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
    min_pnp_inlier_ratio: float = 0.2
    precision: Literal["fp32", "bf16"] = "fp32"
    fusion: Literal["always", "auto"] = "always"

    def __post_init__(self) -> None:
        if self.precision not in ("fp32", "bf16"):
            raise InputError(f"precision must be 'fp32' or 'bf16', got {self.precision!r}")
        if self.fusion not in ("always", "auto"):
            raise InputError(f"fusion must be 'always' or 'auto', got {self.fusion!r}")
        if self.sampling not in ("grid", "topk"):
            raise InputError(f"descriptor sampling must be 'grid' or 'topk', got {self.sampling!r}")
        if self.stride < 1 or self.top_k < 1:
            raise InputError(f"stride ({self.stride}) and top_k ({self.top_k}) must be positive")


# ============================================================================================= the pair stage
@dataclass
class NetworkPair:
    """The ``pair`` stage's output: one forward pass on a pair, on the network grid, on the CPU.

    Attributes:
        net_size: (W, H) of the network input (view 0's working size).
        pts3d: both views' point maps in **camera 0's** frame (metres for the metric checkpoint). [2, H, W, 3]
        conf: point-map confidences (≥ 1). [2, H, W]
        desc: descriptors, fused with DINOv3 features when the fusion ran. [2, H, W, D]
        desc_conf: descriptor confidences, the activation's floor removed (≥ 0). [2, H, W]
        mask: pixels of each view inside the image's alpha mask, on the network grid. [2, H, W] bool
        warps: view ↔ network grid of each view (identity for view 0).
        gaussians: the head's Gaussians of both views (camera-0 frame, B = 1 each), or None.
        seconds: wall time of the forward pass.
        fusion: ``"applied"`` (``desc`` is fused), ``"deferred"`` (``desc`` is the backbone's; the fusion can
            still run: :meth:`NeuralPair.apply_fusion`) or ``"none"`` (no DINOv3/fusion weights).
        fusion_seconds: wall time of a deferred fusion that ran.
    """

    net_size: tuple[int, int]
    pts3d: np.ndarray
    conf: np.ndarray
    desc: np.ndarray
    desc_conf: np.ndarray
    mask: np.ndarray
    warps: tuple[ViewWarp, ViewWarp]
    gaussians: tuple[GaussianMaps, GaussianMaps] | None
    seconds: float
    fusion: Literal["applied", "deferred", "none"] = "none"
    fusion_seconds: float = 0.0


class NeuralPair:
    """The ``pair`` stage: both views through the :class:`PairPredictor` once.

    Everything the module's tensor-in/tensor-out ``forward`` leaves out happens here: the views are
    resampled onto one network grid (:class:`ViewWarp`), moved to ``device``, run under autocast for
    ``precision="bf16"``, timed, and the outputs brought back to the CPU as numpy arrays.

    Args:
        predictor: the network (on ``device``, in eval mode).
        config: neural stage settings (``precision``).
        device: where the predictor runs (``"cpu"`` or ``"cuda"``).
    """

    name = "neural:pair-predictor"

    def __init__(self, predictor: PairPredictor, config: NeuralConfig | None = None, device: str = "cpu") -> None:
        self.predictor = predictor
        self.config = config or NeuralConfig()
        self.device = resolve_device(device)
        self.last: NetworkPair | None = None
        self._images: torch.Tensor | None = None  # [2, 3, H, W] on the device, kept for a deferred fusion

    @property
    def defers_fusion(self) -> bool:
        """Whether the fusion waits until the backbone's descriptors prove too few (``fusion="auto"``)."""
        p = self.predictor
        return (
            self.config.fusion == "auto" and bool(getattr(p, "fusion_enabled", False)) and hasattr(p, "forward_unfused")
        )

    def __call__(self, views: list[View]) -> NetworkPair:
        v0, v1 = views
        dev = self.device
        if self.predictor.input_size is not None:  # a fixed-size ONNX file
            warp0 = ViewWarp.fit((v0.width, v0.height), self.predictor.input_size)
        else:  # as the network was trained: aspect kept, centre crop to multiples of 16
            warp0 = ViewWarp.mast3r((v0.width, v0.height), v0.original_size, self.predictor.square_input)
        net_size = warp0.net_size
        warps = (warp0, ViewWarp.fit((v1.width, v1.height), net_size))
        if not warps[1].identity:
            logger.info(
                "%s is %dx%d, %s %dx%d: resized and centre-cropped to %dx%d for the network",
                v1.name, v1.width, v1.height, v0.name, v0.width, v0.height, *net_size,
            )  # fmt: skip
        rgb = np.stack([w.image(v.image) for w, v in zip(warps, (v0, v1))])  # [2, H, W, 3] in [0, 1]
        mask = np.stack([w.image(v.mask) for w, v in zip(warps, (v0, v1))])
        img = torch.from_numpy(np.ascontiguousarray(rgb, np.float32)).permute(0, 3, 1, 2).to(dev)
        bf16 = self.config.precision == "bf16"
        defer = self.defers_fusion
        t0 = time.perf_counter()
        with torch.no_grad(), torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16):
            if defer:
                pred = prediction_from_outputs(self.predictor.forward_unfused(img[:1], img[1:]))
            else:
                pred = self.predictor.predict(img[:1], img[1:])
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        seconds = time.perf_counter() - t0
        self._images = img if defer else None
        logger.info("network forward pass on %s at %dx%d: %.2f s", dev, *net_size, seconds)
        pred = pred.to("cpu", torch.float32)
        gaussians = None
        if pred.gaussians is not None:
            gaussians = (pred.gaussians[0], pred.gaussians[1])
        self.last = NetworkPair(
            net_size=net_size,
            pts3d=pred.pts3d[0].numpy(),
            conf=pred.conf[0].numpy(),
            desc=pred.desc[0].numpy(),
            desc_conf=pred.desc_conf[0].numpy(),
            mask=mask,
            warps=warps,
            gaussians=gaussians,
            seconds=seconds,
            fusion="deferred" if defer else ("applied" if getattr(self.predictor, "fusion_enabled", False) else "none"),
        )
        return self.last

    def apply_fusion(self, pair: NetworkPair) -> None:
        """Run a deferred semantic fusion on ``pair``'s descriptors (in place); nothing when it is not deferred."""
        if pair.fusion != "deferred":
            return
        assert self._images is not None and pair is self.last, "apply_fusion needs this stage's last pair"
        dev, img = self.device, self._images
        bf16 = self.config.precision == "bf16"
        t0 = time.perf_counter()
        with torch.no_grad(), torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16):
            desc = torch.from_numpy(pair.desc)[None].to(dev)
            fused = self.predictor.fuse_descriptors(desc, img[:1], img[1:])
        pair.desc = fused[0].to("cpu", torch.float32).numpy()
        pair.fusion, pair.fusion_seconds = "applied", time.perf_counter() - t0
        self._images = None
        logger.info("semantic fusion run on demand: %.2f s", pair.fusion_seconds)

    def report(self) -> NeuralReport:
        """The ``neural`` section of the run report (after a run; the files and the load time are the engine's)."""
        p = self.predictor
        last = self.last
        return NeuralReport(
            device=str(self.device),
            network=p.network_name(),
            network_size=list(last.net_size) if last is not None else None,
            forward_s=last.seconds if last is not None else None,
            fusion=self._fusion_report(),
            gaussian_head=p.has_gaussian_head,
            config=dataclasses.asdict(self.config),
        )

    def _fusion_report(self) -> FusionReport:
        p, last = self.predictor, self.last
        if last is None:
            return FusionReport(applied=False, detail=p.fusion_name())
        if last.fusion == "deferred":
            return FusionReport(
                applied=False,
                policy="auto",
                detail="semantic fusion skipped: the backbone's descriptors verified enough matches without it "
                "(--quality fast)",
            )
        out = FusionReport(applied=last.fusion == "applied", detail=p.fusion_detail(last.net_size[::-1]))
        if self.config.fusion == "auto" and last.fusion == "applied":
            out.policy, out.on_demand_s = "auto", last.fusion_seconds
            out.detail += " (on demand: too few matches verified without it)"
        return out
