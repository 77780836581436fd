"""What ``--quality fast`` saves on the neural backend by skipping the semantic fusion while matches verify,
and what a pair that needs it pays (issue 13).

    python -m benchmarks.bench_fusion_skip                      # 512x384, DINOv3 ViT-S/16 and ViT-L/16
    python -m benchmarks.bench_fusion_skip --dino vits16 --threads 2

With fusion "auto" (``--quality fast``) the network pass leaves DINOv3 and the fusion MLP out; they run only
when the backbone's own descriptors verify fewer than ``fallback_min_inliers`` matches, and then the matching
and the pose run a second time on the fused descriptors. So an easy pair saves the DINOv3 + fusion time and a
hard pair pays one more matching + pose pass. Both are measured here with random weights at the released sizes
(the timing does not depend on the values): DINOv3 + fusion on both views, and the filtered matching of two
4-px descriptor grids (12,288 24-d descriptors per view at 512x384, the neural default), median of ``--reps``.
"""

from __future__ import annotations

import argparse
import functools

import numpy as np
import torch

from benchmarks._common import median_seconds
from macsplat_cli.neural.dinov3 import DINOV3_PRESETS, DINOv3Encoder
from macsplat_cli.neural.fusion import FusionConfig, ResidualSemanticFusion, fuse_descriptors
from macsplat_cli.pipeline.matching import MatchConfig, match_features
from macsplat_cli.pipeline.types import Features


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, nargs=2, default=(512, 384), metavar=("W", "H"))
    ap.add_argument("--dino", nargs="+", default=["vits16", "vitl16"], choices=sorted(DINOV3_PRESETS))
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    w, h = args.size
    torch.manual_seed(0)
    img = torch.rand(2, 3, h, w) * 2 - 1
    desc = torch.randn(2, h, w, 24)
    print(f"{w}x{h}, {torch.get_num_threads()} threads, median of {args.reps}\n")
    print("| DINOv3 | parameters (M) | DINOv3 + fusion, both views (s): saved on an easy pair |")
    print("|---|---:|---:|")
    for name in args.dino:
        cfg = DINOV3_PRESETS[name]
        enc = DINOv3Encoder(cfg).eval()
        fusion = ResidualSemanticFusion(FusionConfig(desc_dim=24, dino_dim=cfg.embed_dim)).eval()
        with torch.no_grad():
            s = median_seconds(functools.partial(fuse_descriptors, desc, img, fusion=fusion, encoder=enc), args.reps)
        n = sum(p.numel() for p in enc.parameters()) / 1e6
        print(f"| {name} | {n:.1f} | {s:.2f} |")
    rng = np.random.default_rng(0)
    n = (w // 4) * (h // 4)

    def feats() -> Features:
        d = rng.normal(size=(n, 24)).astype(np.float32)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        xy = rng.uniform(0, [w, h], (n, 2))
        return Features(xy=xy, desc=d, conf=rng.uniform(0, 3, n).astype(np.float32))

    f0, f1 = feats(), feats()
    match_cfg = MatchConfig(conf_threshold=1.0, ratio_confidence=False)
    s = median_seconds(lambda: match_features(f0, f1, match_cfg), args.reps)
    print(f"\nextra matching pass on a hard pair ({n:,} descriptors per view): {s:.2f} s (+ the PnP, tens of ms)")


if __name__ == "__main__":
    main()
