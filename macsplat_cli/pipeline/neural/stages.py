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
descriptor of the other: a full 512×384 map (196 608 per view) is out of reach. The descriptors are
sampled on a 4-px grid (:attr:`NeuralConfig.stride`, 12 288 per view at 512×384); grid matches sit on
grid pixels, up to 2.8 px from the true ones, so :func:`refine_matches` then moves each view-1 pixel to
the best descriptor of the dense map within ±2 px. Measured (grid steps, top-k, dense maps):
benchmarks/history/neural.md.

The network's pass and its working size: :mod:`.pair`.

Symbols: ``H, W`` network input size (view 0's working size), ``D`` descriptor dimension (24).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch

from ...errors import ReconstructionError
from ...gaussians import GaussianMaps
from ...metrics import angle_between_deg, rotation_angle_deg
from ...neural.predictor import PairPredictor
from ...rotations import quat_multiply, rotmat_to_quat_np
from ..pose import fundamental_from_pose, pose_from_pointmap, sampson_distance
from ..run import ReconstructConfig, Stages, classical_stages
from ..slots import PairPass
from ..stages import DepthGaussians, FilteredMatcher
from ..types import DepthMap, Features, Matches, TwoViewGeometry, View
from .geometry import estimate_focal_weiszfeld, pixel_grid, sample_descriptors
from .pair import NetworkPair, NeuralConfig, NeuralPair

__all__ = [
    "NeuralDepth",
    "NeuralDescriptors",
    "NeuralGaussians",
    "NeuralPose",
    "network_pass",
    "neural_stages",
    "refine_matches",
]

logger = logging.getLogger(__name__)


def neural_stages(
    predictor: PairPredictor, config: ReconstructConfig, neural: NeuralConfig | None = None, device: str = "cpu"
) -> Stages:
    """The neural backend's slots: the network's pass, descriptors, pose, depth and Gaussians (the head's, else the
    classical surfels), the rest as :func:`~..run.classical_stages` fills them; metric."""
    neural = neural or NeuralConfig()
    pair = NeuralPair(predictor, neural, device)
    stages = classical_stages(
        config,
        descriptors=NeuralDescriptors(predictor, neural),
        matcher=FilteredMatcher(config.matching),
        pose=NeuralPose(neural),
        depth=NeuralDepth(neural),
        gaussians=NeuralGaussians() if predictor.has_gaussian_head else DepthGaussians(config.gaussians),
        # the fusion is the fallback of the backbone's own descriptors
        fallback=NeuralDescriptors(predictor, neural, fuse_with=pair) if pair.defers_fusion else None,
    )
    return dataclasses.replace(stages, pair=pair, scale="metric")


def network_pass(pair: PairPass) -> NetworkPair:
    """The network's pass a neural stage was handed (:data:`~..slots.PairPass`).

    Raises:
        ValueError: None: a neural stage in a pipeline without the network's ``pair`` slot.
    """
    if pair is None:
        raise ValueError("a neural stage needs the network's pass: build the pipeline with neural_stages")
    return pair


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

    def __call__(self, views: list[View], pair: PairPass) -> list[Features]:
        pair = network_pass(pair)
        if self.fuse_with is not None:
            self.fuse_with.apply_fusion(pair)
        return [self.features(pair, 0), self.features(pair, 1)]


class NeuralPose:
    """Pose stage: focal by Weiszfeld (unknown intrinsics), camera 1 by PnP on the network's point map; metric."""

    name = "neural:mast3r-pointmap-pnp"

    def __init__(self, config: NeuralConfig | None = None) -> None:
        self.config = config or NeuralConfig()

    def __call__(self, v0: View, v1: View, matches: Matches, pair: PairPass) -> TwoViewGeometry:
        cfg = self.config
        pred = network_pass(pair)
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
            focal_evidence="pointmap" if estimated else None, median_parallax_deg=parallax, source="pointmap",
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

    def __call__(self, views: list[View], geometry: TwoViewGeometry, pair: PairPass) -> list[DepthMap]:
        cfg = self.config
        pred = network_pass(pair)
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
        self, views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap], pair: PairPass
    ) -> list[GaussianMaps]:
        pair = network_pass(pair)
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
