"""Rasterizer speed and memory: forward ms, forward+backward ms, peak RSS, minor page faults and CPU a step.

Scene (as in the reference design notes): N Gaussians uniform in [-1, 1]² × [2, 4] in
front of an identity OpenCV camera with focal length = image width, scales 0.005–0.03,
random rotations, opacity logits U(-2, 2), SH degree 0; loss = L1 to a random image.
Each configuration runs in its own process so that peak memory is its own.

    python -m benchmarks.bench_render                 # the table for benchmarks/README.md
    python -m benchmarks.bench_render --sizes 100000:256x256 --reps 5
    python -m benchmarks.bench_render --sizes 1000000:1920x1080 --reps 3 --forward-only
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from typing import TYPE_CHECKING

from benchmarks._common import peak_rss_mib, print_header, render_scene_params, row

if TYPE_CHECKING:
    from macsplat_cli.render.rasterize import Backend

DEFAULT = ["50000:256x256", "100000:256x256", "250000:256x256", "50000:512x384", "100000:512x384", "250000:512x384"]


def _one(n: int, w: int, h: int, reps: int, backend: Backend, backward: bool = True) -> dict:
    import torch

    from macsplat_cli.gaussians import Gaussians
    from macsplat_cli.render import render

    base_rss = peak_rss_mib()
    g, params = render_scene_params(n)
    for p in params:
        p.requires_grad_(True)
    gs = Gaussians(*params)
    K = torch.tensor([[float(w), 0.0, w / 2], [0.0, float(w), h / 2], [0.0, 0.0, 1.0]])
    V = torch.eye(4)
    target = torch.rand(h, w, 3, generator=g)

    def fwd() -> torch.Tensor:
        return render(gs, V, K, w, h, backend=backend).rgb

    def step() -> None:
        for p in params:
            p.grad = None
        (fwd() - target).abs().mean().backward()

    # warm-up (JIT cache load), then timed repetitions
    t0 = time.perf_counter()
    step() if backward else fwd()
    first = time.perf_counter() - t0
    t_fwd, t_tot = [], []
    use = [0, 0.0, 0.0]  # minor page faults, user and system CPU seconds of the timed steps (forwards if no backward)
    for _ in range(reps):
        u0 = _usage()
        t0 = time.perf_counter()
        with torch.no_grad():
            fwd()
        t_fwd.append(time.perf_counter() - t0)
        if backward:
            u0 = _usage()
            t0 = time.perf_counter()
            step()
            t_tot.append(time.perf_counter() - t0)
        use = [a + b - c for a, b, c in zip(use, _usage(), u0)]
    out = render(gs, V, K, w, h, backend=backend)
    peak = peak_rss_mib()
    t_fwd.sort()
    t_tot = sorted(t_tot) or [float("nan")]
    return {
        "n": n,
        "size": f"{w}x{h}",
        "visible": int(out.visible.numel()),
        "intersections": out.n_intersections,
        "fwd_ms": 1e3 * t_fwd[len(t_fwd) // 2],
        "fwd_bwd_ms": 1e3 * t_tot[len(t_tot) // 2],
        "fwd_min_ms": 1e3 * t_fwd[0],
        "fwd_bwd_min_ms": 1e3 * t_tot[0],
        "first_call_s": first,
        "peak_rss_mb": peak,
        "baseline_rss_mb": base_rss,
        "threads": torch.get_num_threads(),
        "faults_per_step": use[0] / reps,
        "user_ms": 1e3 * use[1] / reps,
        "sys_ms": 1e3 * use[2] / reps,
    }


def _usage() -> tuple[int, float, float]:
    """This process's minor page faults, user and system CPU seconds so far."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_minflt, r.ru_utime, r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=DEFAULT, help="N:WxH entries")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--backend", default="numba")
    ap.add_argument("--json", action="store_true", help="print JSON rows instead of a table")
    ap.add_argument("--forward-only", action="store_true", help="time the forward only (no backward at all)")
    ap.add_argument("--_child", nargs=3, metavar=("N", "W", "H"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._child:
        n, w, h = (int(x) for x in args._child)
        print(json.dumps(_one(n, w, h, args.reps, args.backend, backward=not args.forward_only)))
        return
    rows = []
    for spec in args.sizes:
        n, size = spec.split(":")
        w, h = size.split("x")
        cmd = [sys.executable, "-m", "benchmarks.bench_render", "--_child", n, w, h, "--reps", str(args.reps),
               "--backend", args.backend] + (["--forward-only"] if args.forward_only else [])  # fmt: skip
        res = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy(), check=True)
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"backend={args.backend}, threads={rows[0]['threads']}, median (min) of {args.reps} repetitions\n")
    print_header(["Gaussians", "image", "visible", "intersections", "forward ms", "forward+backward ms",
                  "peak RSS MB (baseline)", "faults a step (user / sys ms)"], "rrrrrrrr")  # fmt: skip
    for r in rows:
        print(row([f"{r['n']:,}", r["size"], f"{r['visible']:,}", f"{r['intersections']:,}",
                   f"{r['fwd_ms']:.0f} ({r['fwd_min_ms']:.0f})", f"{r['fwd_bwd_ms']:.0f} ({r['fwd_bwd_min_ms']:.0f})",
                   f"{r['peak_rss_mb']:.0f} ({r['baseline_rss_mb']:.0f})",
                   f"{r['faults_per_step']:,.0f} ({r['user_ms']:.0f} / {r['sys_ms']:.0f})"]))  # fmt: skip


if __name__ == "__main__":
    main()
