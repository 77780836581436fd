"""Pose confidence (issue 14): how many wrong poses are written, refused or caught, by baseline.

    python -m benchmarks.pose_confidence --json after.json                     # this checkout
    cd /tmp && PYTHONPATH=/tmp/head:$REPO python -m benchmarks.pose_confidence --json before.json
        # another checkout's library (/tmp/head/macsplat_cli) with these benchmarks ($REPO: this repository); run
        # from a folder without macsplat_cli: ``-m`` puts the working folder first on the path
    python -m benchmarks.pose_confidence --table before.json after.json        # the tables
    python -m benchmarks.pose_confidence --signals after.json                  # every case's checks
    python -m benchmarks.pose_confidence --angles 45 60 75 90 --min-angle 35 --no-wide --json nowide.json
        # the wide-baseline cases without the second fallback tier (issue 14 item 3); drop --no-wide for with

Cases: ray-traced orbit pairs (``macsplat_cli.datasets.synthetic``, room and object, 10–90°, true field of view
50° and 75°, intrinsics given or not, seeds 0 and 1) and CO3D apple pairs (``--data``, SfM ground truth, 8–105°
between the cameras, intrinsics given or not). Each case runs the classical pipeline up to the final pose and its
confidence (``Pipeline.run`` with a depth stage that stops it: depth and Gaussians do not depend on it) with
``accept_low_confidence=True``, and records the rotation error against the ground truth, the pose stage's doubts,
the confidence and its checks, and the times (to the pose, and of the ``pose confidence`` stage, from the pipeline's
``on_stage`` events). An outcome is "right" below 5° rotation error, "wrong" at 5° or more,
"refused" when the pipeline raised (no pose) or, after, when a doubt or a failed check refuses it. On a checkout
without the confidence (``--json`` from there), every pose it returns is written.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import progress, write_json
from benchmarks._pose_cases import outcome, pose_case
from macsplat_cli.cameras import CameraSet, save_cameras
from macsplat_cli.datasets import Frame
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.datasets.co3d import load_co3d_json
from macsplat_cli.images import save_image
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.pipeline.views import ViewConfig

CO3D_PAIRS = [
    (0, 1), (2, 5), (3, 4), (16, 18), (14, 17), (1, 4), (0, 5), (14, 19), (13, 15), (0, 15), (4, 6), (5, 6),
    (12, 13), (0, 14), (1, 15), (2, 6), (5, 16), (5, 7), (0, 6), (0, 13), (3, 7), (6, 18), (5, 13), (0, 7),
]  # fmt: skip


def run_case(paths: list[Path], cfg: ReconstructConfig, R_gt: np.ndarray, t_gt: np.ndarray) -> dict[str, Any]:
    r = pose_case(paths, cfg, R_gt, t_gt)
    r.pop("doubt_checks", None)  # this benchmark's records stay as they were (``compare_json``)
    r.pop("tier", None)
    return r


def synthetic_cases(angles: list[float], seeds: list[int]) -> list[dict[str, Any]]:
    return [
        {"set": "synthetic", "kind": kind, "angle": angle, "fov": fov, "seed": seed, "given": given}
        for kind in ("room", "object") for angle in angles for fov in (50, 75) for seed in seeds
        for given in (True, False)
    ]  # fmt: skip


def co3d_cases(data: Path) -> list[dict[str, Any]]:
    if not (data / "co3d_apple" / "cameras_opencv.json").is_file():
        return []
    return [{"set": "co3d", "a": a, "b": b, "given": given} for a, b in CO3D_PAIRS for given in (True, False)]


@functools.lru_cache(maxsize=2)
def _co3d_frames(data: Path) -> list[Frame]:
    return load_co3d_json(data / "co3d_apple")[0].frames


def prepare(
    case: dict[str, Any], data: Path, tmp: Path
) -> tuple[list[Path], ReconstructConfig, np.ndarray, np.ndarray]:
    cfg = ReconstructConfig()
    key = "_".join(f"{k}{v}" for k, v in case.items())
    if case["set"] == "synthetic":
        scene = S.make_scene(case["kind"], seed=0)
        c0, c1 = S.orbit_pair(scene, case["angle"], seed=case["seed"], fov_deg=case["fov"])
        paths = []
        for cam in (c0, c1):
            p = tmp / f"{key}_{cam.name}.png"
            save_image(p, S.render(scene, cam).image)
            paths.append(p)
        cams = [c0, c1]
        R, t = S.relative_pose(c0, c1)
    else:
        frames = _co3d_frames(data)
        pair = [frames[case["a"]], frames[case["b"]]]
        paths = [f.image for f in pair]
        cams = [f.camera for f in pair]
        T = cams[1].world_to_cam @ cams[0].cam_to_world
        R, t = T[:3, :3], T[:3, 3]
        case["angle"] = round(rotation_error_deg(cams[0].cam_to_world[:3, :3], cams[1].cam_to_world[:3, :3]), 1)
    if case["given"]:
        save_cameras(tmp / f"{key}.json", CameraSet(cams))
        cfg.views = ViewConfig(intrinsics=tmp / f"{key}.json")
    return paths, cfg, R, t


def _band(case: dict[str, Any]) -> str:
    a = case["angle"]
    if case["set"] == "synthetic":
        return f"{a:g}°"
    for lo, hi in ((0, 15), (15, 35), (35, 60), (60, 90), (90, 181)):
        if lo <= a < hi:
            return f"{lo}–{hi}°" if hi < 181 else f"≥{lo}°"
    return "?"


def table(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> None:
    """Per set, scene, baseline and intrinsics: right / wrong / refused before and after, and the times."""
    key = lambda r: json.dumps(r["case"], sort_keys=True)  # noqa: E731
    b_by = {key(r): r for r in before}
    groups: dict[tuple, list[tuple[dict, dict]]] = defaultdict(list)
    for r in after:
        c = r["case"]
        g = (c["set"], c.get("kind", "apple"), _band(c), "given" if c["given"] else "estimated")
        groups[g].append((b_by.get(key(r), {"result": {"failed": "not run"}}), r))
    print("| set | scene | baseline | intrinsics | pairs | before: right / wrong / refused | "
          "after: right / wrong / refused | to the pose, s: before → after (median) | "
          "confidence s (median, max) |")  # fmt: skip
    print("|---|---|---|---|---:|---|---|---|---|")
    tot: defaultdict[tuple[str, str, str], int] = defaultdict(int)
    for g in sorted(groups, key=lambda g: (g[0], g[1], _sort_band(g[2]), g[3])):
        rows = groups[g]
        cb = [outcome(b["result"], refusals=True) for b, _ in rows]
        ca = [outcome(a["result"], refusals=True) for _, a in rows]
        tb = np.median([b["result"]["time_s"] for b, _ in rows if "time_s" in b["result"]] or [math.nan])
        ta = np.median([a["result"]["time_s"] for _, a in rows])
        tc = [a["result"].get("confidence_s", math.nan) for _, a in rows if "failed" not in a["result"]] or [math.nan]
        fmt = lambda xs: f"{xs.count('right')} / {xs.count('wrong')} / {xs.count('refused')}"  # noqa: E731
        wrong_after = ca.count("wrong")
        print(f"| {g[0]} | {g[1]} | {g[2]} | {g[3]} | {len(rows)} | {fmt(cb)} | "
              f"{fmt(ca)}{' ⚠' if wrong_after else ''} | {tb:.2f} → {ta:.2f} | "
              f"{np.median(tc):.3f}, {max(tc):.3f} |")  # fmt: skip
        for name, xs in (("before", cb), ("after", ca)):
            for o in ("right", "wrong", "refused"):
                tot[(g[0], name, o)] += xs.count(o)
    print()
    for s in sorted({k[0] for k in tot}):
        print(f"{s}: before {tot[(s, 'before', 'right')]} right / {tot[(s, 'before', 'wrong')]} wrong / "
              f"{tot[(s, 'before', 'refused')]} refused; after {tot[(s, 'after', 'right')]} right / "
              f"{tot[(s, 'after', 'wrong')]} wrong / {tot[(s, 'after', 'refused')]} refused")  # fmt: skip


def _sort_band(b: str) -> float:
    digits = "".join(ch if ch.isdigit() or ch == "." else " " for ch in b).split()
    return float(digits[0]) if digits else 0.0


def signals(after: list[dict[str, Any]]) -> None:
    """Every case with a pose: its error, whether it was refused and by what, and the checks."""
    print("| case | rot err ° | refused by | confidence | checks |")
    print("|---|---:|---|---:|---|")
    for r in sorted((r for r in after if "failed" not in r["result"]), key=lambda r: r["result"]["rot"]):
        res, c = r["result"], r["case"]
        name = " ".join(f"{k}={v}" for k, v in c.items() if k != "set")
        by = "; ".join(d[:60] for d in res["doubts"]) or "–"
        checks = ", ".join(f"{k} {v:.3g}" for k, v in res["checks"].items())
        conf = res["confidence"]
        print(f"| {c['set']} {name} | {res['rot']:.2f} | {by} | {conf if conf is None else f'{conf:.2f}'} | {checks} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("../shared/data"), help="the shared data folder (CO3D)")
    ap.add_argument("--angles", type=float, nargs="+", default=[10, 20, 30, 45, 60, 75, 90])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--only", choices=["synthetic", "co3d"], help="run one set only")
    ap.add_argument("--min-angle", type=float, default=0.0, help="run only the cases at least this wide (CO3D: °)")
    ap.add_argument("--no-wide", action="store_true", help="without the second fallback tier (the chain before it)")
    ap.add_argument("--json", type=Path, help="run the cases and write the results here")
    ap.add_argument("--table", type=Path, nargs=2, metavar=("BEFORE", "AFTER"), help="print the comparison")
    ap.add_argument("--signals", type=Path, metavar="AFTER", help="print every case's checks")
    args = ap.parse_args()
    if args.table:
        table(json.loads(args.table[0].read_text()), json.loads(args.table[1].read_text()))
        return
    if args.signals:
        signals(json.loads(args.signals.read_text()))
        return
    if args.json is None:
        ap.error("give --json OUT to run the cases, or --table / --signals to read results")
    cases = []
    if args.only in (None, "synthetic"):
        cases += synthetic_cases(args.angles, args.seeds)
    if args.only in (None, "co3d"):
        cases += co3d_cases(args.data)
    tmp = Path(tempfile.mkdtemp())
    results = []
    for case in cases:
        paths, cfg, R, t = prepare(case, args.data, tmp)
        if case["angle"] < args.min_angle:
            continue
        if args.no_wide:
            search: Any = getattr(cfg, "search", cfg)  # a checkout before issue 24 has the fields on the config
            search.wide = False
            search.plane_tiebreak_margin = None
        res = run_case(paths, cfg, R, t)
        results.append({"case": case, "result": res})
        msg = res.get("failed", "")[:70] or f"rot {res['rot']:.2f}° doubts {len(res['doubts'])}"
        progress(f"{case} {msg} {res['time_s']:.2f}s")
        write_json(args.json, results, indent=1, default=float)


if __name__ == "__main__":
    main()
