"""The learned matcher (issue 39) on the development pairs: the pose of each pair with ``--matcher sift``, ``auto``
and ``aliked``, pose stage only (stages 1 and 4: no depth, no Gaussians).

    python -m benchmarks.learned_dev --data ../shared/data [--matchers sift auto] [--modes given est]
        [--scenes co3d icl_livingroom] [--keypoints 2048] [--detect-size 1024]

For each pair (``accuracy_dev.CASES``, and ``--extra`` ones) and intrinsics mode (``given``: the data's; ``est``: the
60° prior): the tier that gave the pose, its verified matches, the rotation and translation-direction errors against
the ground truth, or the refusal (``--show-refused``: the refused pose's errors too, its first doubt as the outcome),
the learned tier's seconds (its descriptors, LightGlue and pose; wall and this process's CPU time, which a loaded
machine inflates less; the model load is done and timed once before the pairs), its two stages' CPU seconds (ALIKED
on both photos, LightGlue) and the whole search's (wall). ``--threads 1`` times one core (torch's threads), the
figure that load inflates least. A pose ≥ 5° off that is accepted is marked ``WRONG``. Peak memory (max RSS) at the
end. Measured: benchmarks/history/learned.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import peak_rss_mib, row, rule
from benchmarks._dev import c2w, dev_frames, save_intrinsics
from benchmarks.accuracy_dev import CASES
from macsplat_cli.engine import EngineConfig
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.metrics import rotation_error_deg, translation_direction_error_deg
from macsplat_cli.pipeline.learned import LearnedConfig
from macsplat_cli.pipeline.learned.models import learned_models
from macsplat_cli.pipeline.matching import MatchConfig
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, classical_stages
from macsplat_cli.pipeline.stages import FilteredMatcher
from macsplat_cli.pipeline.views import ViewConfig, load_views

WRONG_DEG = 5.0
"""An accepted pose this far off (rotation or translation direction) is wrong (the issue's target)."""


def run_pair(frames: list, pair: tuple[int, int], given: bool, matcher: str, learned: LearnedConfig,
             show_refused: bool = False, filtered_tau: float | None = None) -> list[str]:  # fmt: skip
    f0, f1 = frames[pair[0]], frames[pair[1]]
    cfg = ReconstructConfig(views=ViewConfig())
    if given:
        cfg.views.intrinsics = save_intrinsics(Path(tempfile.mkdtemp()) / "k.json", (f0, f1))
    cfg.search = dataclasses.replace(cfg.search, learned=learned)
    settings = EngineConfig(pipeline=cfg, matcher=matcher).settings()  # type: ignore[arg-type]
    if show_refused:  # the refused pose kept, its doubts listed, to read its error
        settings.pipeline.search = dataclasses.replace(settings.pipeline.search, accept_low_confidence=True)
    stages = None
    if filtered_tau is not None:  # ALIKED's descriptors through our filtered matcher instead of LightGlue
        stages = classical_stages(settings.pipeline, matcher=FilteredMatcher(MatchConfig(conf_threshold=filtered_tau)))
    pipe = Pipeline(settings.pipeline, stages)
    views = load_views([f0.image, f1.image], settings.pipeline.views)
    times: dict[str, tuple[float, float]] = {}

    def timed(stage, fn):  # noqa: ANN001, ANN202
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        times[stage] = (time.perf_counter() - t, time.process_time() - c)
        return out

    t0 = time.perf_counter()
    try:
        res = pipe.search(views, None, timed)
    except ReconstructionError as e:
        res, reason = None, str(e)
    total = time.perf_counter() - t0
    suffix = "" if matcher == "aliked" else " (learned)"
    ran = [times[k] for k in (f"descriptors{suffix}", f"matching{suffix}", f"pose{suffix}") if k in times]
    ran = ran if matcher != "sift" else []
    learned_s = f"{sum(w for w, _ in ran):.1f} / {sum(c for _, c in ran):.1f}" if ran else "–"
    split = f"{ran[0][1]:.2f} / {ran[1][1]:.2f}" if len(ran) >= 2 else "–"
    if res is None:
        return ["refused", "–", "–", "–", reason[:90], learned_s, split, f"{total:.1f}"]
    T = np.linalg.inv(c2w(f1)) @ c2w(f0)
    rot = rotation_error_deg(res.geometry.R, T[:3, :3])
    tr = translation_direction_error_deg(res.geometry.t, T[:3, 3])
    mark = " WRONG" if max(rot, tr) >= WRONG_DEG else ""
    outcome = f"refused: {res.doubts[0].message[:80]}" if res.doubts else "accepted" + mark
    return [res.tier + (" +guided" if res.guided else ""), str(len(res.geometry.inliers)), f"{rot:.2f}",
            f"{tr:.2f}", outcome, learned_s, split, f"{total:.1f}"]  # fmt: skip


def _pair_arg(text: str) -> tuple[int, int]:
    """``--extra``'s frame pair ``i,j``."""
    i, j = map(int, text.split(","))
    return i, j


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the shared dev data folder")
    ap.add_argument("--matchers", nargs="+", default=["sift", "auto"])
    ap.add_argument("--modes", nargs="+", default=["given", "est"])
    ap.add_argument("--scenes", nargs="+", default=["co3d", "icl_livingroom", "nyu_dining"])
    ap.add_argument("--pairs", nargs="+", default=None, help="only these pair names (e.g. 'wide 55°' '(2,3)')")
    ap.add_argument("--keypoints", type=int, default=LearnedConfig.max_keypoints)
    ap.add_argument("--detect-size", type=int, default=LearnedConfig.detect_size)
    ap.add_argument("--depth-confidence", type=float, default=LearnedConfig.depth_confidence)
    ap.add_argument("--width-confidence", type=float, default=LearnedConfig.width_confidence)
    ap.add_argument("--extra", nargs="+", default=[], metavar="SCENE:I,J",
                    help="more pairs by frame position (0-based, dev_frames' order), e.g. co3d:5,8")  # fmt: skip
    ap.add_argument("--show-refused", action="store_true",
                    help="a refused pose's error too (the search keeps it; first doubt: the outcome)")  # fmt: skip
    ap.add_argument("--threads", type=int, default=None, help="torch's threads (default: torch's own)")
    ap.add_argument("--filtered-tau", type=float, default=None,
                    help="with --matchers aliked: ALIKED's descriptors through our filtered matcher (reciprocal "
                         "nearest neighbours, ratio confidence, the gate c0·c1 > τ) instead of LightGlue")  # fmt: skip
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    learned = LearnedConfig(max_keypoints=args.keypoints, detect_size=args.detect_size,
                            depth_confidence=args.depth_confidence, width_confidence=args.width_confidence)  # fmt: skip
    print(f"learned: {learned}; torch threads {torch.get_num_threads()}")
    if any(m != "sift" for m in args.matchers):
        t, c = time.perf_counter(), time.process_time()
        learned_models(learned)
        print(f"model load (kornia's import, files, sha256, build): {time.perf_counter() - t:.2f} s wall, "
              f"{time.process_time() - c:.2f} s CPU")  # fmt: skip
    print(row(["scene", "pair", "intrinsics", "matcher", "tier", "verified", "rot err °", "t err °", "outcome",
               "learned s (wall / CPU)", "ALIKED / LightGlue CPU s", "search s"]))  # fmt: skip
    print(rule("lllllrrrlrrr"))
    cache: dict[str, list] = {}
    extra = [(sc, f"({e.split(',')[0]},{e.split(',')[1]})#", _pair_arg(e))
             for sc, e in (x.split(":") for x in args.extra)]  # fmt: skip
    for scene, name, pair in [*CASES, *extra]:
        if scene not in args.scenes or (args.pairs and name not in args.pairs and not name.endswith("#")):
            continue
        frames = cache.setdefault(scene, dev_frames(args.data, scene))
        for mode in args.modes:
            for matcher in args.matchers:
                cells = run_pair(frames, pair, mode == "given", matcher, learned, args.show_refused, args.filtered_tau)
                print(row([scene, name, mode, matcher, *cells]), flush=True)
    print(f"\npeak memory (max RSS): {peak_rss_mib():.0f} MiB")


if __name__ == "__main__":
    main()
