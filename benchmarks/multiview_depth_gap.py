"""Is the N-photo depth what the refinement cannot fix? Fused depth against the truth, and a scene built from the
true depth (issue 41, item 4).

    python -m benchmarks.multiview_depth_gap            # object, room; 4, 8 photos; balanced; fused, gt, gt-covis
    python -m benchmarks.multiview_depth_gap --qualities balanced,best --modes fused,gt-covis,gt
    python -m benchmarks.multiview_depth_gap --scenes icl,nyu --views 5,3 --modes fused --data /work/shared/data

The reconstruction runs as ``benchmarks.multiview_gain`` (ray-traced orbits: object, room) or
``benchmarks.multiview_dev`` (ICL, NYU: their sensor / rendered depth) run it; the N-photo depth stage
(``pipeline/multiview/depth.multiview_depths``) is wrapped: its output, each registered photo's fused depth, is
compared with the true depth of that photo at the working size, in our units — on the ray-traced orbits the true
scene ray-cast through the registered camera mapped into the true world (the similarity of
``multiview_dev.similarity``, registered cameras against the true ones), so that depth and poses agree; on the dev
scenes the depth file resized (nearest) and scaled. Per photo (the table: the mean over the photos), over the pixels
with both a fused and a true depth: the relative error ``|d - d_true| / d_true``, median and 90th percentile, the
median signed error ("bias"), the share above 5 % over all of them, over those another registered photo sees too
("seen": its true surface point in that photo's image at that photo's true depth) and over the others ("alone");
"alone %" is the others' share, "cover" the share of the true depth's pixels the fused depth has.

Modes (``--modes``), every one from the same registration and poses:

* **fused**: today's depth (the run is today's run);
* **gt**: the true depth on the fused depth's pixels, its confidence and ``measured`` kept (accuracy alone);
* **gt-covis**: as gt, but only on the pixels another registered photo sees too (by the true depths): the most a
  depth from the co-visible neighbours could give; the fused depth elsewhere;
* **gt-all**: the true depth on every pixel that has one, confidence 1 (accuracy and completeness);
* **gt-scale**: the fused depth times one factor per photo, the median ratio of the true depth to it (a depth
  bias shared by every pixel, as a registration's scale or pose error would leave it, removed).

Printed per scene, N, quality and mode: the depth errors (the fused depth's, every mode), the held-out PSNR by
target group and its difference from the ``fused`` run of the same invocation ("Δ"; list fused first), the wall
seconds; with ``--per-photo``, each photo's depth after the table, its bias over all, the measured and the filled
pixels apart (a photo off the registered scale is off in its measured pixels; one off only in its filled pixels
carries the fill's guess where nothing measured it). Nothing is written but the ray-traced photos' cache and
``--json``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import macsplat_cli.pipeline.multiview.run as mv_run
from benchmarks import multiview_dev as dev
from benchmarks import multiview_gain as gain
from benchmarks._common import print_header, row, write_json
from benchmarks._dev import c2w, dev_frames
from macsplat_cli.cameras import Camera
from macsplat_cli.datasets.base import read_depth
from macsplat_cli.datasets.synthetic import make_scene, render
from macsplat_cli.pipeline.multiview.register import Registration
from macsplat_cli.pipeline.types import DepthMap

MODES = ("fused", "gt", "gt-covis")
SEEN = 0.02
"""A photo sees another's true surface point when its own true depth there agrees within this (relative)."""
OFF = 0.05
"""A fused depth this much (relative) off the truth counts as wrong."""

Truth = Callable[[str, np.ndarray, int, int, np.ndarray], np.ndarray]
"""``(photo name, K, W, H, cam-to-world in the true world) → true depth [H, W]`` (0: no surface)."""


@dataclass
class DepthStats:
    """The fused depth of one photo against the truth (shares in [0, 1])."""

    median: float
    p90: float
    bias: float
    """The median signed relative error (fused / true − 1)."""
    off: float
    off_seen: float
    """The share > :data:`OFF` off among the pixels another photo sees too."""
    off_alone: float
    """… among the pixels no other photo sees."""
    alone: float
    """The share of the fused pixels no other photo sees."""
    cover: float
    measured: float = math.nan
    """The share of the fused pixels whose depth a depth pair measured (the rest: the fill's guess)."""
    bias_measured: float = math.nan
    """The median signed relative error over the measured pixels: the photo's depth scale against the registered
    one (a fill's guess does not move it; the fused ``bias`` is mostly the fill's where little is measured)."""
    bias_filled: float = math.nan
    """… over the filled pixels."""
    name: str = ""


@dataclass
class Case:
    """One run: the depth stats of every registered photo, the PSNR by target group, seconds, error."""

    depth: list[DepthStats] = field(default_factory=list)
    psnr: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    error: str = ""


def depth_stats(d: DepthMap, gt: np.ndarray, seen: np.ndarray) -> DepthStats:
    """``d`` [H, W] against the true depth ``gt`` [H, W] (same units); ``seen``: :func:`seen_elsewhere`."""
    both = d.valid & (gt > 0)
    rel = np.abs(d.depth - gt) / np.where(gt > 0, gt, 1.0)
    if not both.any():
        nan = math.nan
        return DepthStats(nan, nan, nan, nan, nan, nan, nan, 0.0)
    off = rel > OFF
    share = [float(off[both & m].mean()) if (both & m).any() else math.nan for m in (seen, ~seen)]
    measured = d.valid if d.measured is None else d.measured
    biases = [float(np.median(d.depth[m] / gt[m] - 1)) if m.any() else math.nan
              for m in (both, both & measured, both & ~measured)]  # fmt: skip
    return DepthStats(float(np.median(rel[both])), float(np.percentile(rel[both], 90)), biases[0],
                      float(off[both].mean()), share[0], share[1], float((both & ~seen).sum() / both.sum()),
                      float(both.sum() / (gt > 0).sum()), float((both & measured).sum() / both.sum()),
                      biases[1], biases[2])  # fmt: skip


def seen_elsewhere(k: int, gts: dict[int, np.ndarray], reg: Registration) -> np.ndarray:
    """Pixels of photo ``k`` whose true surface point another photo of ``gts`` (photo → true depth [H, W], our
    units) sees (in its image, its true depth there within :data:`SEEN`). [H, W] bool"""
    g = gts[k]
    ys, xs = np.nonzero(g > 0)
    z = g[ys, xs]
    rays = np.stack([xs + 0.5, ys + 0.5, np.ones_like(z)], 1) @ np.linalg.inv(reg.K[k]).T
    X = (rays * z[:, None] - reg.t[k]) @ reg.R[k]
    seen = np.zeros(z.size, bool)
    for j, gj in gts.items():
        if j == k:
            continue
        Xj = X @ reg.R[j].T + reg.t[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = Xj @ reg.K[j].T
            u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        h, w = gj.shape
        inside = (Xj[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        there = gj[np.clip(np.nan_to_num(v), 0, h - 1).astype(int), np.clip(np.nan_to_num(u), 0, w - 1).astype(int)]
        seen |= inside & (np.abs(Xj[:, 2] - there) <= SEEN * there)
    out = np.zeros(g.shape, bool)
    out[ys[seen], xs[seen]] = True
    return out


def replaced(d: DepthMap, gt: np.ndarray, mode: str, seen: np.ndarray) -> DepthMap:
    """The depth the run goes on with in ``mode`` (module docstring); ``seen``: :func:`seen_elsewhere`."""
    if mode == "gt-scale":
        both = d.valid & (gt > 0)
        f = float(np.median(gt[both] / d.depth[both])) if both.any() else 1.0
        return DepthMap((d.depth * f).astype(np.float32), d.confidence, d.measured)
    if mode in ("gt", "gt-covis"):
        keep = d.valid & (gt > 0) & (seen if mode == "gt-covis" else True)
        if mode == "gt-covis":
            return DepthMap(np.where(keep, gt, d.depth).astype(np.float32), d.confidence, d.measured)
        measured = None if d.measured is None else d.measured & keep
        return DepthMap(np.where(keep, gt, 0).astype(np.float32), np.where(keep, d.confidence, 0).astype(np.float32),
                        measured)  # fmt: skip
    return DepthMap(gt.astype(np.float32), (gt > 0).astype(np.float32), None)


@contextlib.contextmanager
def depth_hook(truth: Truth, poses: dict[str, np.ndarray], mode: str, case: Case) -> Iterator[None]:
    """While active, every N-photo depth stage records its fused depths' errors in ``case`` and, unless ``mode``
    is fused, goes on with the true depth. ``poses``: photo name → true cam-to-world [4, 4]."""
    original = mv_run.multiview_depths

    def wrapped(views, reg, two_view):  # noqa: ANN001, ANN202
        depths, pairs = original(views, reg, two_view)
        ks = [k for k, d in enumerate(depths) if d is not None]
        s, R, t = dev.similarity([reg.cam_to_world(k) for k in ks], [poses[views[k].name] for k in ks])
        gts = {}
        for k in ks:
            T = reg.cam_to_world(k)
            Tg = np.eye(4)
            Tg[:3, :3], Tg[:3, 3] = R.T @ T[:3, :3], R.T @ (T[:3, 3] - t) / s
            h, w = views[k].image.shape[:2]
            gts[k] = truth(views[k].name, reg.K[k], w, h, Tg) * s
        out = list(depths)
        for k in ks:
            d = depths[k]
            assert d is not None  # ks: the photos with a depth
            seen = seen_elsewhere(k, gts, reg)
            case.depth.append(dataclasses.replace(depth_stats(d, gts[k], seen), name=views[k].name))
            if mode != "fused":
                out[k] = replaced(d, gts[k], mode, seen)
        return out, pairs

    mv_run.multiview_depths = wrapped
    try:
        yield
    finally:
        mv_run.multiview_depths = original


def orbit_case(kind: str, n: int, quality: str, mode: str, cache: Path) -> Case:
    """``benchmarks.multiview_gain``'s N-photo run of one orbit in ``mode``."""
    o = gain.orbit(kind, n, 45.0, cache)
    scene = make_scene(kind, 0)  # type: ignore[arg-type]
    poses = {p.stem: T for p, T in zip(o.photos, o.poses)}

    def truth(name: str, K: np.ndarray, w: int, h: int, T: np.ndarray) -> np.ndarray:
        return render(scene, Camera(name, w, h, K, T), supersample=1).depth.astype(np.float64)

    case = Case()
    with depth_hook(truth, poses, mode, case):
        r = gain.run(o, range(n), quality)
    case.psnr, case.seconds, case.error = r.psnr, r.seconds, r.error
    return case


def dev_case(scene: str, n: int, quality: str, mode: str, data: Path) -> Case:
    """``benchmarks.multiview_dev``'s known-K run of ``n`` contexts of a dev scene in ``mode``; PSNR over its
    targets as group "mid"."""
    frames = dev_frames(data, dev.SCENE_NAMES[scene])
    ctx = dev.contexts(len(frames), n)
    tgts = dev.targets(len(frames), ctx)
    byname = {f.image.stem: f for f in frames}
    poses = {k: c2w(f) for k, f in byname.items()}

    def truth(name: str, K: np.ndarray, w: int, h: int, T: np.ndarray) -> np.ndarray:
        f = byname[name]
        assert f.depth is not None
        d = read_depth(f.depth, f.depth_scale).astype(np.float64)
        H0, W0 = d.shape
        ys = np.minimum(((np.arange(h) + 0.5) * H0 / h).astype(int), H0 - 1)
        xs = np.minimum(((np.arange(w) + 0.5) * W0 / w).astype(int), W0 - 1)
        return d[ys[:, None], xs[None, :]]

    dev.SETTINGS["quality"] = quality
    case = Case()
    with depth_hook(truth, poses, mode, case):
        out = dev.run_ours(frames, ctx, tgts, True, 512)
    case.seconds, case.error = out.seconds, (out.error or "")[:80]
    if out.target_psnr:
        case.psnr = {"mid": float(np.mean(list(out.target_psnr.values())))}
    return case


def _stats_cells(c: Case) -> list[str]:
    if not c.depth:
        return ["–"] * 4

    def pc(attr: str) -> float:
        return 100 * float(np.nanmean([getattr(d, attr) for d in c.depth]))

    return [f"{pc('median'):.2f} / {pc('p90'):.1f} / {pc('bias'):+.2f}",
            f"{pc('off'):.1f} / {pc('off_seen'):.1f} / {pc('off_alone'):.0f}",
            f"{pc('alone'):.1f}", f"{pc('cover'):.0f}"]  # fmt: skip


def per_photo_rows(record: dict) -> list[list[str]]:
    """One record's photos as table cells: a photo whose depth is off in all but its measured pixels carries a
    fill's guess (nothing measured the rest), one off in its measured pixels too is off the registered scale."""
    head = [record["scene"], str(record["n"]), record["quality"], record["mode"]]
    return [head + [d["name"], f"{100 * d['median']:.1f}",
                    f"{100 * d['bias']:+.1f} / {100 * d['bias_measured']:+.1f} / {100 * d['bias_filled']:+.1f}",
                    f"{100 * d['measured']:.0f}", f"{100 * d['alone']:.0f}"] for d in record["depth"]]  # fmt: skip


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="object,room", help="object, room (ray-traced orbits), icl, nyu (dev data)")
    p.add_argument("--views", default="4,8")
    p.add_argument("--qualities", default="balanced")
    p.add_argument("--modes", default=",".join(MODES))
    p.add_argument("--data", type=Path, default=Path("/work/shared/data"), help="the shared data folder (icl, nyu)")
    p.add_argument("--cache", type=Path, default=gain.DEFAULT_CACHE)
    p.add_argument("--json", type=Path)
    p.add_argument("--per-photo", action="store_true", help="after the table, each photo's depth (per_photo_rows)")
    args = p.parse_args(argv)
    print_header(["scene", "N", "quality", "mode", "rel err % med / p90 / bias",
                  "> 5 % off: all / seen / alone", "alone %", "cover %",
                  "mid PSNR (Δ)", "side PSNR (Δ)", "s"], "lllllrrrrrr")  # fmt: skip
    records = []
    for kind in args.scenes.split(","):
        for n in (int(v) for v in args.views.split(",")):
            for q in args.qualities.split(","):
                base: dict[str, float] = {}
                for mode in args.modes.split(","):
                    t0 = time.perf_counter()
                    c = (orbit_case(kind, n, q, mode, args.cache) if kind in ("object", "room")
                         else dev_case(kind, n, q, mode, args.data))  # fmt: skip
                    if mode == "fused":
                        base = dict(c.psnr)
                    cells = [kind, str(n), q, mode + (f" {c.error}" if c.error else ""), *_stats_cells(c)]
                    for g in ("mid", "side"):
                        v, b = c.psnr.get(g, math.nan), base.get(g, math.nan)
                        cells.append("–" if math.isnan(v) else f"{v:.2f} ({v - b:+.2f})")
                    print(row(cells + [f"{time.perf_counter() - t0:.1f}"]), flush=True)
                    records.append({"scene": kind, "n": n, "quality": q, "mode": mode, "psnr": c.psnr,
                                    "depth": [d.__dict__ for d in c.depth], "seconds": c.seconds,
                                    "error": c.error})  # fmt: skip
    if args.per_photo:
        print()
        print_header(["scene", "N", "quality", "mode", "photo", "rel err % med", "bias %: all / measured / filled",
                      "measured %", "alone %"], "lllllrrrr")  # fmt: skip
        for r in records:
            for line in per_photo_rows(r):
                print(row(line))
    if args.json:
        write_json(args.json, records)
    sys.exit(0)


if __name__ == "__main__":
    main()
