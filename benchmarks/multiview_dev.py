"""N photos on the development scenes: registration, pose error and held-out views, next to pycolmap (issue 26).

    python -m benchmarks.multiview_dev                                   # co3d, icl, nyu; N = 2, 3, 5, 8
    python -m benchmarks.multiview_dev --scenes co3d --views 3,5 --table # only the table (no progress, no notes)

Per scene and N (context views evenly spaced over the first ``--frames`` frames of the sequence):

* **ours, known K**: ``reconstruct`` on the N context photos with their true intrinsics (a cameras file per run,
  cameras named after the photo files); for CO3D also **without** intrinsics (focal error: median over the
  registered photos of f_est / f_true - 1 at the original size, f = sqrt(fx fy)).
* **registered/N**, and the relative-rotation error over every pair of registered photos (gauge-free:
  ``benchmarks._colmap_peer.align_rotation_errors``), median / max, degrees.
* **held-out PSNR**: targets are up to 3 frames strictly between the first and last context, never a context of
  any N in 2, 3, 5, 8 that leaves a frame out (so the targets are the same for every N where possible; else the
  non-context frames of this N). Our registered cameras are aligned to the ground truth by a similarity: the
  rotation from every registered camera's orientation (chordal mean), scale and translation from their centres
  (:func:`similarity`; until 2026-11-28 Umeyama on the centres alone, which mis-rotated short arcs). Each
  target's true camera is mapped into our frame (known K: its true K; unknown: our first camera's K) and rendered at
  the working size; PSNR against the target photo resized to it. "align °" is the median rotation residual of that
  alignment over the registered cameras.
* **copy**: the nearest context photo (camera-centre distance, ties by viewing-direction angle) as the prediction.
* **best 2-view** (known K, N ≥ 3, targets present): ours on each adjacent context pair alone (2 photos); per
  target the best PSNR among those pairs, averaged over the targets (an oracle choice of the pair).
* **COLMAP**: ``benchmarks._colmap_peer.run_colmap`` with the true K (held fixed) on the same contexts, known-K
  rows only: registered/N, relative-rotation error, seconds.
* **s**: wall seconds of our ``reconstruct`` (loading to compaction; not the scoring).
* **note**: the refinement's resolution where one ran (``--quality best``: with the photos' sharp-minus-pooled gain
  that chose it, issue 41), the photos left out.

Frame indices are 0-based positions in the loader's list (ICL/NYU frame ``i`` is ``color/{i + 1}.png``). ICL and
NYU hold 5 frames each: N = 8 is skipped there and N = 5 leaves no target. A ReconstructionError is caught per run
and its message printed in the row; after the table, every left-out photo with its reason.

The data sets are third-party and not in the repository (``--data``, the shared data folder); the frames come from
``benchmarks._dev.dev_frames``. Run from the repository root.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks._colmap_peer import align_rotation_errors, colmap_available, run_colmap
from benchmarks._common import print_header, progress, row, write_json
from benchmarks._dev import c2w, dev_frames, load_rgb, photo_size
from macsplat_cli.camera_math import rescale_intrinsics
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import Frame
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.metrics import psnr, rotation_error_deg
from macsplat_cli.pipeline.run import ReconstructConfig, Reconstruction
from macsplat_cli.pipeline.views import working_size
from macsplat_cli.presets import DEFAULT_MATCHER, MATCHERS, Overrides
from macsplat_cli.render import render_camera

SCENE_NAMES = {"co3d": "co3d", "icl": "icl_livingroom", "nyu": "nyu_dining"}
"""``--scenes`` names → ``benchmarks._dev`` scene names."""
STANDARD_VIEWS = (2, 3, 5, 8)
"""The N whose contexts the targets avoid (independent of ``--views``, so the targets do not depend on it)."""
MAX_TARGETS = 3
"""Held-out targets per case."""
HEADER = [
    "scene", "N", "K", "contexts", "targets", "registered", "rot err ° med / max", "focal err %", "align °",
    "PSNR", "copy PSNR", "best 2-view PSNR", "s", "COLMAP reg", "COLMAP rot ° med / max", "COLMAP s", "note",
]  # fmt: skip
ALIGNS = "lrllllrrrrrrrlrrl"


@dataclass
class Outcome:
    """One run of ours on some context frames: what registered and the held-out scores."""

    seconds: float
    error: str | None = None
    """The ReconstructionError's message when it failed."""
    registered: list[bool] = field(default_factory=list)
    """Per context frame."""
    rot_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Relative-rotation errors over the registered pairs, degrees. [P]"""
    focal_error_pct: float = math.nan
    """Median signed focal error of the registered photos (estimated intrinsics only), percent."""
    align_deg: float = math.nan
    """Median rotation residual of the similarity alignment over the registered photos, degrees."""
    target_psnr: dict[int, float] = field(default_factory=dict)
    """Target frame index → PSNR of our render."""
    unregistered: dict[int, str] = field(default_factory=dict)
    """Frame index → the photo's name and why it was left out."""
    refine: str = ""
    """The refinement's resolution, with the photos' sharp-minus-pooled gain where they chose it (the note)."""


# ------------------------------------------------------------------------------------------ case layout
def contexts(n_frames: int, n: int) -> list[int]:
    """``n`` frame indices evenly spaced over ``0 .. n_frames - 1`` (distinct)."""
    return sorted({int(round(x)) for x in np.linspace(0, n_frames - 1, n)})


def targets(n_frames: int, ctx: Sequence[int]) -> list[int]:
    """Up to :data:`MAX_TARGETS` frames strictly between the first and last context, none a context; preferring
    frames that no standard N (:data:`STANDARD_VIEWS`, those leaving a frame out) uses as a context, spread evenly
    over the candidates."""
    used: set[int] = set()
    for n in STANDARD_VIEWS:
        if n < n_frames:
            used |= set(contexts(n_frames, n))
    inside = [i for i in range(ctx[0] + 1, ctx[-1]) if i not in ctx]
    pool = [i for i in inside if i not in used] or inside
    k = min(MAX_TARGETS, len(pool))
    return [pool[int((j + 0.5) * len(pool) / k)] for j in range(k)]


def save_intrinsics(path: Path, frames: Sequence[Frame]) -> Path:
    """The frames' true intrinsics as a cameras file, one camera per photo named after its file; ``path``."""
    save_cameras(path, CameraSet([Camera(f.image.name, *photo_size(f), f.camera.K, np.eye(4)) for f in frames]))
    return path


# ------------------------------------------------------------------------------------------ geometry
def similarity(est: Sequence[np.ndarray], gt: Sequence[np.ndarray]) -> tuple[float, np.ndarray, np.ndarray]:
    """Ground-truth world → our world, from every registered camera's orientation and centre: the rotation is the
    chordal mean of ``R_est R_gtᵀ`` over the cameras, then scale and translation by least squares on the centres
    given it. est, gt: cam-to-world [4, 4] each, ≥ 2 cameras at distinct centres.

    Why not Umeyama on the centres alone: cameras on a short arc are nearly collinear, and the centres leave the
    rotation about the arc's chord badly determined — on a synthetic 45° orbit registered to 0.02°, the centres'
    rotation was 0.19° off every camera, which moves a held-out view by ~1.5 px and cost its render 2 dB
    (benchmarks/history/multiview_joint.md)."""
    M = sum(E[:3, :3] @ G[:3, :3].T for E, G in zip(est, gt))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt
    ce, cg = np.array([T[:3, 3] for T in est]), np.array([T[:3, 3] for T in gt])
    a = cg @ R.T
    da, de = a - a.mean(0), ce - ce.mean(0)
    s = float((da * de).sum() / (da**2).sum())
    return s, R, ce.mean(0) - s * a.mean(0)


def mapped(T: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """A ground-truth cam-to-world [4, 4] in our world (rotation R·R_T, centre s·R·c + t)."""
    out = np.eye(4)
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = s * R @ T[:3, 3] + t
    return out


def nearest_context(frames: Sequence[Frame], ctx: Sequence[int], ti: int) -> int:
    """The context frame nearest to target ``ti``: by camera-centre distance, ties by viewing-direction angle."""
    T = c2w(frames[ti])

    def key(i: int) -> tuple[float, float]:
        C = c2w(frames[i])
        cos = float(np.clip(C[:3, 2] @ T[:3, 2], -1.0, 1.0))
        return round(float(np.linalg.norm(C[:3, 3] - T[:3, 3])), 9), math.degrees(math.acos(cos))

    return min(ctx, key=key)


# ------------------------------------------------------------------------------------------ our runs
SETTINGS: dict[str, Any] = {"quality": "balanced", "far_layer": True, "pairs": True, "matcher": DEFAULT_MATCHER}
"""``--quality``, ``--no-far-layer``, ``--matcher`` (for every run of ours, the N-view and the two-view ones alike),
``--no-pairs``."""


def run_ours(frames: Sequence[Frame], ctx: Sequence[int], tgts: Sequence[int], known: bool, size: int) -> Outcome:
    """Ours on the context frames ``ctx`` (true intrinsics when ``known``), scored on ``tgts``."""
    cf = [frames[i] for i in ctx]
    cfg = ReconstructConfig()
    cfg.background.enabled = bool(SETTINGS["far_layer"])
    with tempfile.TemporaryDirectory(prefix="mv_dev_") as tmp:
        if known:
            cfg.views.intrinsics = save_intrinsics(Path(tmp) / "cameras.json", cf)
        t0 = time.perf_counter()
        try:
            config = EngineConfig(
                quality=SETTINGS["quality"], matcher=SETTINGS["matcher"], overrides=Overrides(size=size), pipeline=cfg
            )
            rec = reconstruct([f.image for f in cf], config)
        except ReconstructionError as e:
            return Outcome(time.perf_counter() - t0, error=str(e))
        out = Outcome(time.perf_counter() - t0)
    score(rec, frames, ctx, tgts, known, out)
    out.refine = refine_note(rec) if rec.report.refine is not None else ""
    return out


def refine_note(rec: Reconstruction) -> str:
    """``1/scale`` of the refinement, with the photos' sharp-minus-pooled gain where they chose it; "–": none ran."""
    r = rec.report.refine
    if r is None:
        return "–"
    gain = (r.joint or {}).get("sharp_gain_db")
    return f"1/{r.scale}" + (f" ({gain:+.2f})" if gain is not None else "")


def score(
    rec: Reconstruction, frames: Sequence[Frame], ctx: Sequence[int], tgts: Sequence[int], known: bool, out: Outcome
) -> None:
    """Fill ``out``: registration, rotation and focal errors, the alignment and the targets' PSNR."""
    stem = {frames[i].image.stem: k for k, i in enumerate(ctx)}
    cams = {stem[c.name]: c for c in rec.cameras()}
    out.registered = [k in cams for k in range(len(ctx))]
    out.unregistered = {ctx[stem[u["name"]]]: f"{u['name']}: {u['reason']}" for u in rec.cameras().unregistered}
    gt = [c2w(frames[i]) for i in ctx]
    est = [cams[k].cam_to_world if k in cams else None for k in range(len(ctx))]
    out.rot_errors = align_rotation_errors(est, gt)
    reg = sorted(cams)
    if not known:
        ratios = [math.sqrt(cams[k].K[0, 0] * cams[k].K[1, 1] / (gt_K[0, 0] * gt_K[1, 1])) - 1.0
                  for k in reg for gt_K in [frames[ctx[k]].camera.K]]  # fmt: skip
        out.focal_error_pct = 100.0 * float(np.median(ratios))
    s, R, t = similarity([cams[k].cam_to_world for k in reg], [gt[k] for k in reg])
    out.align_deg = float(np.median([rotation_error_deg(R @ gt[k][:3, :3], cams[k].cam_to_world[:3, :3])
                                     for k in reg]))  # fmt: skip
    work = rec.cameras(original_size=False)[0]
    K_ours = work.K
    scene = rec.gaussians
    for ti in tgts:
        ft = frames[ti]
        w, h = photo_size(ft)
        K = rescale_intrinsics(ft.camera.K, work.width / w, work.height / h) if known else K_ours
        cam = Camera(f"t{ti}", work.width, work.height, K, mapped(c2w(ft), s, R, t))
        out.target_psnr[ti] = render_psnr(scene, cam, ft)


def render_psnr(scene: Gaussians, cam: Camera, target: Frame) -> float:
    """PSNR of ``scene`` rendered into ``cam`` against the target photo resized to the camera's size."""
    with torch.no_grad():
        pred = render_camera(scene, cam).rgb.clamp(0, 1).numpy()
    return psnr(pred, load_rgb(target.image, (cam.width, cam.height)))


def copy_psnr(frames: Sequence[Frame], ctx: Sequence[int], ti: int, size: tuple[int, int]) -> float:
    """PSNR of the nearest context photo against target ``ti``, both resized to ``size`` = (W, H)."""
    near = frames[nearest_context(frames, ctx, ti)]
    return psnr(load_rgb(near.image, size), load_rgb(frames[ti].image, size))


# ------------------------------------------------------------------------------------------ one scene
@dataclass
class Case:
    """One row: a scene, N, the intrinsics mode and what was measured."""

    scene: str
    n: int
    known: bool
    ctx: list[int]
    tgts: list[int]
    ours: Outcome | None = None
    copy: dict[int, float] = field(default_factory=dict)
    best_two_view: float | None = None
    two_view_note: str = ""
    colmap: dict | None = None
    skipped: str = ""


class TwoViewCache:
    """Ours on two context frames (known K), scored on every target of the scene, run once per pair."""

    def __init__(self, frames: Sequence[Frame], scene_targets: Sequence[int], size: int) -> None:
        self.frames, self.scene_targets, self.size = frames, list(scene_targets), size
        self.runs: dict[tuple[int, int], Outcome] = {}

    def get(self, pair: tuple[int, int]) -> Outcome:
        if pair not in self.runs:
            self.runs[pair] = run_ours(self.frames, pair, self.scene_targets, True, self.size)
        return self.runs[pair]

    def best(self, ctx: Sequence[int], tgts: Sequence[int]) -> tuple[float | None, str]:
        """Per target the best PSNR among the adjacent context pairs, averaged; and a note on failed pairs."""
        pairs = list(zip(ctx[:-1], ctx[1:]))
        runs = {p: self.get(p) for p in pairs}
        failed = [p for p, r in runs.items() if r.error is not None]
        note = f"2-view failed on {len(failed)}/{len(pairs)} pairs" if failed else ""
        best = [max((r.target_psnr[t] for r in runs.values() if r.error is None), default=math.nan) for t in tgts]
        return (float(np.mean(best)) if best else None), note


def scene_cases(scene: str, frames: list[Frame], views: Sequence[int], known_only: bool = False) -> list[Case]:
    """The rows of one scene: known K for every N that fits, also unknown K on CO3D (unless ``known_only``)."""
    cases = []
    for n in views:
        for known in (True, False) if scene == "co3d" and not known_only else (True,):
            if n > len(frames):
                cases.append(Case(scene, n, known, [], [], skipped=f"only {len(frames)} frames"))
                continue
            ctx = contexts(len(frames), n)
            cases.append(Case(scene, n, known, ctx, targets(len(frames), ctx)))
    return cases


def run_case(case: Case, frames: list[Frame], two_view: TwoViewCache, size: int, with_colmap: bool) -> None:
    """Fill one case: ours, the copy baseline, the best two-view and the COLMAP peer."""
    wh = working_size(*photo_size(frames[case.ctx[0]]), size)
    case.copy = {t: copy_psnr(frames, case.ctx, t, wh) for t in case.tgts}
    if case.n == 2 and case.known:
        case.ours = two_view.get((case.ctx[0], case.ctx[1]))  # the same run, scored on every scene target
    else:
        case.ours = run_ours(frames, case.ctx, case.tgts, case.known, size)
    if case.known and case.n >= 3 and case.tgts and SETTINGS.get("pairs", True):
        case.best_two_view, case.two_view_note = two_view.best(case.ctx, case.tgts)
    if case.known and with_colmap:
        cf = [frames[i] for i in case.ctx]
        run = run_colmap([f.image for f in cf], K=[f.camera.K for f in cf], max_image_size=512)
        rot = align_rotation_errors(run.cam_to_world, [c2w(f) for f in cf])
        case.colmap = {"registered": run.n_registered, "rot": rot.tolist(), "seconds": run.seconds,
                       "error": run.error}  # fmt: skip


# ------------------------------------------------------------------------------------------ table
def _med_max(errs: Sequence[float] | np.ndarray) -> str:
    return f"{np.median(errs):.2f} / {np.max(errs):.2f}" if len(errs) else "–"


def _num(x: float | None, fmt: str = ".2f") -> str:
    return "–" if x is None or not math.isfinite(x) else format(x, fmt)


def table_row(case: Case) -> str:
    """The printed row of one case."""
    head = [case.scene, str(case.n), "known" if case.known else "unknown"]
    if case.skipped:
        return row(head + [""] * (len(HEADER) - 4) + [case.skipped])
    head += [",".join(map(str, case.ctx)), ",".join(map(str, case.tgts)) or "–"]
    o = case.ours
    assert o is not None
    copy = float(np.mean(list(case.copy.values()))) if case.copy else None
    cm = case.colmap
    col = ["–", "–", "–"] if cm is None else [f"{cm['registered']}/{case.n}", _med_max(cm["rot"]),
                                              f"{cm['seconds']:.1f}"]  # fmt: skip
    if cm is not None and cm["error"]:
        col[1] = "failed"
    best = _num(case.best_two_view) if case.known and case.n >= 3 and case.tgts else "–"
    if o.error is not None:
        return row(head + [f"0/{case.n}", "–", "–", "–", "–", _num(copy), best, f"{o.seconds:.1f}", *col,
                           "failed: " + o.error])  # fmt: skip
    psnr_ = float(np.mean([o.target_psnr[t] for t in case.tgts])) if case.tgts else None
    left = ",".join(map(str, sorted(o.unregistered)))
    refined = f"refined at {o.refine}" if o.refine else ""
    note = "; ".join(x for x in (refined, f"left out: {left}" if left else "", case.two_view_note) if x)
    focal = "–" if case.known else _num(o.focal_error_pct, "+.1f")
    return row(head + [
        f"{sum(o.registered)}/{case.n}", _med_max(o.rot_errors), focal, _num(o.align_deg), _num(psnr_), _num(copy),
        best, f"{o.seconds:.1f}", *col, note,
    ])  # fmt: skip


def notes(cases: Sequence[Case]) -> list[str]:
    """Why each left-out photo was left out, and COLMAP's failures (printed after the table)."""
    lines = []
    for c in cases:
        tag = f"{c.scene} N={c.n} {'known' if c.known else 'unknown'} K"
        for i, why in c.ours.unregistered.items() if c.ours is not None else ():
            lines.append(f"- {tag}: frame {i} ({why})")
        if c.colmap is not None and c.colmap["error"]:
            lines.append(f"- {tag}: COLMAP: {c.colmap['error']}")
    return lines


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/work/shared/data"), help="the shared data folder")
    ap.add_argument("--scenes", default="co3d,icl,nyu", help="comma-separated: co3d, icl, nyu")
    ap.add_argument("--views", default="2,3,5,8", help="comma-separated N")
    ap.add_argument("--frames", type=int, default=24, help="use the first this many frames of each sequence")
    ap.add_argument("--size", type=int, default=512, help="the working size (long side)")
    ap.add_argument("--no-colmap", action="store_true", help="skip the pycolmap peer")
    ap.add_argument("--quality", default="balanced", help="our runs' --quality (fast, balanced, best)")
    ap.add_argument("--matcher", default=DEFAULT_MATCHER, choices=MATCHERS, help="our runs' --matcher")
    ap.add_argument("--no-far-layer", action="store_true", help="our runs without the far background layer")
    ap.add_argument("--known-only", action="store_true", help="only the known-K rows (CO3D: no unknown-K row)")
    ap.add_argument("--no-pairs", action="store_true", help="skip the best 2-view column (its runs are unchanged)")
    ap.add_argument("--table", action="store_true", help="print only the table (no progress, no notes)")
    ap.add_argument("--json", type=Path, help="also write every case as JSON")
    args = ap.parse_args(argv)
    SETTINGS.update(
        quality=args.quality, far_layer=not args.no_far_layer, pairs=not args.no_pairs, matcher=args.matcher
    )
    views = [int(v) for v in args.views.split(",")]
    with_colmap = not args.no_colmap and colmap_available()
    say = (lambda m: None) if args.table else progress
    if not with_colmap:
        say("COLMAP peer skipped" + ("" if args.no_colmap else " (pycolmap is not installed)"))
    print_header(HEADER, ALIGNS)
    cases: list[Case] = []
    t0 = time.perf_counter()
    for key in args.scenes.split(","):
        scene = SCENE_NAMES[key]
        frames = dev_frames(args.data, scene)[: args.frames]
        sc = scene_cases(key, frames, views, args.known_only)
        scene_targets = sorted({t for c in sc for t in c.tgts})
        two_view = TwoViewCache(frames, scene_targets, args.size)
        for case in sc:
            if not case.skipped:
                say(f"{key} N={case.n} {'known' if case.known else 'unknown'} K: contexts {case.ctx} ...")
                run_case(case, frames, two_view, args.size, with_colmap)
            print(table_row(case), flush=True)
            cases.append(case)
    say(f"total {time.perf_counter() - t0:.0f} s")
    if not args.table:
        print("\n".join(["", *notes(cases)]))
    if args.json:
        write_json(args.json, [vars(c) for c in cases], default=lambda o: o.tolist() if hasattr(o, "tolist")
                   else vars(o))  # fmt: skip


if __name__ == "__main__":
    main()
