"""The neural backend: MASt3R (optionally with DINOv3 semantic fusion and a Splatt3R Gaussian head) in the stage slots.

The network runs **once per pair**, as the pipeline's ``pair`` stage (:class:`NeuralPair`: the
views onto the network grid, :class:`~macsplat_cli.neural.predictor.PairPredictor`, the outputs back
to numpy as a :class:`NetworkPair`); every later stage receives that one prediction explicitly:

=============  ==========================================================================================
stage          what it does with the prediction
=============  ==========================================================================================
descriptors    the 24-d MASt3R descriptors (fused with DINOv3 features when ``--dino``/``--fusion`` are
               given), subsampled on a regular grid, with the descriptor confidence
matching       the shared :class:`~..stages.FilteredMatcher` (reciprocal NN, ``c0·c1 > τ``), unchanged
pose           focal length of view 0 from its own point map (Weiszfeld), unless intrinsics were given;
               camera 1 from view 1's pixels and their 3-D points in camera 0 (PnP + RANSAC); metric;
               accepted as the classical pose is (:func:`~..pose.accept_pose`, in the pose search)
depth          z of each view's point map in its own camera frame; confidence from ``conf``
gaussians      the Splatt3R head's per-pixel Gaussians, or the classical surfels from that depth
=============  ==========================================================================================

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

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from ...errors import InputError, ReconstructionError
from ...gaussians import GaussianMaps
from ...metrics import angle_between_deg, rotation_angle_deg
from ...neural.predictor import PairPredictor, prediction_from_outputs, resolve_device
from ...rotations import quat_multiply, rotmat_to_quat_np
from ..matching import MatchConfig
from ..pose import fundamental_from_pose, pose_from_pointmap, sampson_distance
from ..run import ReconstructConfig
from ..stages import DepthGaussians, FilteredMatcher
from ..types import DepthMap, Features, Matches, TwoViewGeometry, View
from .geometry import estimate_focal_weiszfeld, pixel_grid, sample_descriptors
from .warp import ViewWarp

__all__ = [
    "NetworkPair",
    "NeuralConfig",
    "NeuralDepth",
    "NeuralDescriptors",
    "NeuralGaussians",
    "NeuralPair",
    "NeuralPose",
    "neural_reconstruct_config",
    "neural_stages",
    "refine_matches",
]

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
            point maps are not one rigid scene seen by two cameras: the pose is doubted (``geometry.doubts``; refused
            unless ``--accept-low-confidence``, as every doubt of :func:`~..pose.accept_pose`).
        precision: ``"fp32"``, or ``"bf16"`` (autocast: matrix products in bfloat16, 1.8× faster on
            a CPU with AVX512-BF16 in ``benchmarks/bench_neural.py``; accuracy with the official
            weights unmeasured).
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


def neural_reconstruct_config(config: ReconstructConfig | None = None) -> ReconstructConfig:
    """``config`` (or the default) adapted to the neural stages.

    The SIFT fallback and the epipolar-guided re-matching are turned off (the pose does not come
    from the matches), and the matcher uses the learned confidence as is (``ratio_confidence=False``)
    with ``τ = 1`` on ``c0·c1`` (the descriptor confidence ``exp(x)``; MASt3R's visloc keeps pixels whose
    confidence exceeds 1.001).
    """
    c = dataclasses.replace(config) if config is not None else ReconstructConfig()
    c.search = dataclasses.replace(c.search, fallback_descriptors=None, guided_band_px=None)
    c.matching = MatchConfig(conf_threshold=1.0, ratio_confidence=False, max_block_elems=c.matching.max_block_elems)
    return c


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

    def report(self) -> dict[str, Any]:
        """The ``neural`` section of the run report (after a run)."""
        p = self.predictor
        last = self.last
        return {
            "device": str(self.device),
            "network": p.network_name(),
            "network_size": list(last.net_size) if last is not None else None,
            "forward_s": last.seconds if last is not None else None,
            "fusion": self._fusion_report(),
            "gaussian_head": p.has_gaussian_head,
            "config": dataclasses.asdict(self.config),
        }

    def _fusion_report(self) -> dict[str, Any]:
        p, last = self.predictor, self.last
        if last is None:
            return {"applied": False, "detail": p.fusion_name()}
        if last.fusion == "deferred":
            return {
                "applied": False,
                "policy": "auto",
                "detail": "semantic fusion skipped: the backbone's descriptors verified enough matches without it "
                "(--quality fast)",
            }
        out: dict[str, Any] = {"applied": last.fusion == "applied", "detail": p.fusion_detail(last.net_size[::-1])}
        if self.config.fusion == "auto" and last.fusion == "applied":
            out.update(policy="auto", on_demand_s=last.fusion_seconds)
            out["detail"] += " (on demand: too few matches verified without it)"
        return out


def neural_stages(
    predictor: PairPredictor, config: ReconstructConfig, neural: NeuralConfig | None = None, device: str = "cpu"
) -> dict[str, Any]:
    """The neural stage callables (keyword arguments of :class:`~..run.Pipeline`)."""
    neural = neural or NeuralConfig()
    gaussians = NeuralGaussians() if predictor.has_gaussian_head else DepthGaussians(config.gaussians)
    pair = NeuralPair(predictor, neural, device)
    stages: dict[str, Any] = {
        "pair": pair,
        "descriptors": NeuralDescriptors(predictor, neural),
        "matcher": FilteredMatcher(config.matching),
        "pose": NeuralPose(neural),
        "depth": NeuralDepth(neural),
        "gaussians": gaussians,
    }
    if pair.defers_fusion:  # the fusion is the fallback of the backbone's own descriptors
        stages["fallback_descriptors"] = NeuralDescriptors(predictor, neural, fuse_with=pair)
    return stages


def refine_matches(pred: NetworkPair, matches: Matches, radius: int) -> Matches:
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


def _scale_of_512(w: int, h: int) -> float:
    return max(w, h) / 512.0


# ============================================================================================= stages
class NeuralDescriptors:
    """Descriptor stage: the network's (fused) dense descriptors, subsampled, with their confidence."""

    def __init__(
        self, predictor: PairPredictor, config: NeuralConfig | None = None, *, fuse_with: NeuralPair | None = None
    ) -> None:
        self.config = config or NeuralConfig()
        self.fuse_with = fuse_with
        if fuse_with is not None:
            fusion = f"+{predictor.fusion_name()} (on demand)"
        elif predictor.fusion_enabled and (config is None or config.fusion == "always"):
            fusion = "+" + predictor.fusion_name()
        elif predictor.fusion_enabled:
            fusion = " (semantic fusion when too few matches verify)"
        else:
            fusion = " (semantic fusion skipped)"
        self.name = f"neural:mast3r-desc{predictor.desc_dim}{fusion}"

    def features(self, pair: NetworkPair, k: int) -> Features:
        """View ``k``'s sampled descriptors, pixel coordinates in the view's working grid."""
        cfg = self.config
        wn, hn = pair.net_size
        idx, grid = sample_descriptors(
            pair.desc_conf[k], sampling=cfg.sampling, stride=cfg.stride, top_k=cfg.top_k, mask=pair.mask[k]
        )
        uv = np.stack([idx % wn + 0.5, idx // wn + 0.5], 1).astype(np.float64)
        d = pair.desc[k].reshape(hn * wn, -1)[idx]
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return Features(
            xy=pair.warps[k].from_net(uv),
            desc=np.ascontiguousarray(d, np.float32),
            conf=np.ascontiguousarray(pair.desc_conf[k].reshape(-1)[idx], np.float32),
            grid=grid,
        )

    def __call__(self, views: list[View], pair: NetworkPair) -> list[Features]:
        if self.fuse_with is not None:
            self.fuse_with.apply_fusion(pair)
        return [self.features(pair, 0), self.features(pair, 1)]


class NeuralPose:
    """Pose stage: focal by Weiszfeld (unknown intrinsics), camera 1 by PnP on the network's point map; metric."""

    name = "neural:mast3r-pointmap-pnp"

    def __init__(self, config: NeuralConfig | None = None) -> None:
        self.config = config or NeuralConfig()

    def __call__(self, v0: View, v1: View, matches: Matches, pair: NetworkPair) -> TwoViewGeometry:
        cfg = self.config
        pred = pair
        wn, hn = pred.net_size
        px = _scale_of_512(wn, hn)
        ok = (pred.conf > cfg.conf_threshold) & pred.mask & (np.isfinite(pred.pts3d).all(-1))  # [2, H, W]
        info: dict[str, float | int | str | bool] = {}
        K0, K1 = v0.K.copy(), v1.K.copy()
        estimated = False
        if v0.intrinsics_source == "prior":
            K0n = pred.warps[0].K_net(K0)  # view 0 on the network grid (resized/cropped for a fixed-size network)
            f0n = estimate_focal_weiszfeld(
                pred.pts3d[0], (K0n[0, 2], K0n[1, 2]), mask=ok[0], iters=cfg.weiszfeld_iters,
                focal_base=float(K0n[0, 0]), focal_range=cfg.focal_range,
            )  # fmt: skip
            f0 = f0n / float(np.mean(pred.warps[0].scale))
            info["focal_prior_px"] = float(K0[0, 0])
            K0[0, 0] = K0[1, 1] = f0
            estimated = True
        if v1.intrinsics_source == "prior":
            # View 1's own-frame point map needs a second pass; assume view 0's field of view (one camera).
            f1 = float(K0[0, 0]) * max(v1.width, v1.height) / max(v0.width, v0.height)
            K1[0, 0] = K1[1, 1] = f1
            estimated = True

        K1n = pred.warps[1].K_net(K1)
        sel = np.flatnonzero(ok[1].reshape(-1))
        if len(sel) > cfg.pnp_max_points:
            sel = sel[np.linspace(0, len(sel) - 1, cfg.pnp_max_points).astype(np.int64)]
        uv1 = pixel_grid(hn, wn)[sel]
        X1 = pred.pts3d[1].reshape(-1, 3)[sel].astype(np.float64)
        pnp = pose_from_pointmap(
            uv1, X1, K1n, threshold_px=cfg.pnp_reproj_px * px, iterations=cfg.pnp_iters,
            min_points=cfg.min_pose_points,
        )  # fmt: skip
        R, t = pnp.R, pnp.t
        n_in = int(pnp.inliers.sum())
        pnp_ratio = n_in / max(len(sel), 1)
        doubts: list[str] = []
        if pnp_ratio < cfg.min_pnp_inlier_ratio:
            doubts.append(
                f"pose confidence low: the network's point maps are not consistent with one camera pose: only {n_in} "
                f"of {len(sel)} confident pixels ({100 * pnp_ratio:.0f} %) agree with the PnP pose, need "
                f"{100 * cfg.min_pnp_inlier_ratio:.0f} %"
            )
        # parallax over view 0's confident points
        X0 = pred.pts3d[0][ok[0]].astype(np.float64)
        parallax = float(np.nanmedian(angle_between_deg(X0, X0 + R.T @ t))) if len(X0) else float("nan")
        radius = cfg.stride // 2 if cfg.sampling == "grid" else 1
        n_candidates = len(matches)
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
            pnp_inlier_ratio=pnp_ratio,
            inlier_ratio=len(inl) / max(n_candidates, 1),  # verified / candidate matches, as the classical pose's
            pnp_median_reprojection_px=pnp.median_error_px,
            inliers=len(inl),
            median_sampson_px=sampson,
            rotation_deg=rotation_angle_deg(R),
            translation_norm=float(np.linalg.norm(t)),
            scale="metric",
        )
        logger.debug("neural pose: %s", info)
        return TwoViewGeometry(
            R=R, t=t, K0=K0, K1=K1, inliers=inl, diagnostics=info, doubts=doubts, focal_estimated=estimated,
            # the focal was measured on the point map, not the matches: the acceptance does not ask them for it
            focal_evidence="pointmap" if estimated else None, median_parallax_deg=parallax,
        )  # fmt: skip

    @staticmethod
    def _verify(
        pred: NetworkPair, ok0: np.ndarray, matches: Matches, R: np.ndarray, t: np.ndarray, K1: np.ndarray,
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

    def __init__(self, config: NeuralConfig | None = None) -> None:
        self.config = config or NeuralConfig()

    def __call__(self, views: list[View], geometry: TwoViewGeometry, pair: NetworkPair) -> list[DepthMap]:
        cfg = self.config
        pred = pair
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
    (camera 0) quantities, which is what :meth:`GaussianMaps.to_gaussians` assumes. Pixels with a depth
    (confident, in front of the camera, inside the alpha mask) carry a Gaussian.
    """

    name = "neural:splatt3r-gaussian-head"

    def __call__(
        self, views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap], pair: NetworkPair
    ) -> list[GaussianMaps]:
        if pair.gaussians is None:
            raise ValueError("NeuralGaussians needs the Gaussian head's outputs")
        out = []
        for k, (g, v, d) in enumerate(zip(pair.gaussians, views, depths)):
            means, quats = g.means[0].double(), g.quats[0].double()  # [Hn, Wn, ·]
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
                "sh": g.sh[0].reshape(*means.shape[:2], -1),
            }
            warp = pair.warps[k]
            on_view = {n: torch.from_numpy(np.ascontiguousarray(warp.sample(a.numpy())[0])) for n, a in maps.items()}
            h, w = v.height, v.width
            out.append(
                GaussianMaps(
                    means=on_view["means"][None],
                    log_scales=on_view["log_scales"][None],
                    quats=on_view["quats"][None],
                    opacity_logits=on_view["opacity_logits"][None, ..., 0],
                    sh=on_view["sh"].reshape(1, h, w, -1, 3),
                    valid=torch.from_numpy(np.ascontiguousarray(d.valid))[None],
                    cam_to_world=torch.from_numpy(geometry.cam_to_world(k))[None],
                )
            )
        return out
