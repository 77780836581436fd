"""Our Numba rasterizer against gsplat on CUDA: do the images and gradients agree, and how fast is each?

The scene of ``bench_render.py`` (N Gaussians uniform in [-1, 1]² × [2, 4] before an identity OpenCV camera, SH
degree 0, loss = L1 to a random image). For each size: forward and forward+backward of the Numba CPU kernels
(float32, this machine's cores) and of the peer on the same Gaussians; the peer's image against ours (largest and
mean absolute difference, PSNR) and each parameter's gradient against ours (cosine similarity, relative norm).

    python -m benchmarks.gsplat_parity                        # on a CUDA machine with gsplat installed
    python -m benchmarks.gsplat_parity --peer torch --sizes 2000:64x48   # the plain-PyTorch twin as the peer (CPU)

Without CUDA or gsplat, ``--peer gsplat`` prints why and exits 0. Differences expected by design: gsplat clamps alpha
at 0.999 (we at 0.99) and culls by its own 3-sigma rule, so the images agree to about 1e-3, not to rounding.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from benchmarks._common import print_header, render_scene_params, row

if TYPE_CHECKING:
    from macsplat_cli.render.rasterize import Backend

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _scene(n: int, w: int, h: int, device: str):  # noqa: ANN202 - torch imported lazily
    import torch

    from macsplat_cli.gaussians import Gaussians

    g, params = render_scene_params(n)
    params = [p.to(device).requires_grad_(True) for p in params]
    K = torch.tensor([[float(w), 0.0, w / 2], [0.0, float(w), h / 2], [0.0, 0.0, 1.0]], device=device)
    target = torch.rand(h, w, 3, generator=g).to(device)
    return params, Gaussians(*params), K, torch.eye(4, device=device), target


def _timed(fn: Callable[[], object], sync: Callable[[], None], reps: int) -> float:
    """Median wall seconds of ``fn`` after one warm-up call."""
    fn()
    sync()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def _run(backend: Backend, device: str, n: int, w: int, h: int, reps: int) -> dict:
    import torch

    from macsplat_cli.render import render

    params, gs, K, V, target = _scene(n, w, h, device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

    def forward() -> torch.Tensor:
        return render(gs, V, K, w, h, backend=backend).rgb

    def step() -> None:
        for p in params:
            p.grad = None
        (forward() - target).abs().mean().backward()

    out: dict[str, Any] = {"fwd_ms": 1e3 * _timed(forward, sync, reps), "fwd_bwd_ms": 1e3 * _timed(step, sync, reps)}
    out["rgb"] = forward().detach().float().cpu()
    out["grads"] = {name: p.grad.detach().double().cpu() for name, p in zip(PARAMS, params)}
    return out


def _compare(ours: dict, peer: dict) -> list[str]:
    import torch

    diff = (ours["rgb"] - peer["rgb"]).abs()
    psnr = -10 * torch.log10((diff**2).mean().clamp_min(1e-20))
    cells = [f"{diff.max():.2e}", f"{diff.mean():.2e}", f"{psnr:.1f}"]
    for name in ("means", "log_scales", "opacity_logits", "sh"):
        a, b = ours["grads"][name].flatten(), peer["grads"][name].flatten()
        cos = float(a @ b / (a.norm() * b.norm()).clamp_min(1e-30))
        cells.append(f"{cos:.4f} / {float(b.norm() / a.norm().clamp_min(1e-30)):.3f}")
    return cells


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--peer", choices=("gsplat", "torch"), default="gsplat")
    p.add_argument("--sizes", default="100000:256x256,100000:512x384,1000000:1920x1080",
                   help="N:WxH, comma-separated")  # fmt: skip
    p.add_argument("--reps", type=int, default=3)
    args = p.parse_args(argv)

    import torch

    device = "cuda" if args.peer == "gsplat" else "cpu"
    if args.peer == "gsplat" and not (torch.cuda.is_available() and importlib.util.find_spec("gsplat")):
        print("gsplat on CUDA is not available here: nothing to compare")
        return 0
    if device == "cuda":
        from importlib.metadata import version

        print(f"peer: gsplat {version('gsplat')} on {torch.cuda.get_device_name()}; ours: numba on "
              f"{torch.get_num_threads()} CPU threads; torch {torch.__version__}\n")  # fmt: skip
    timing = ["ours fwd ms", "ours fwd+bwd ms", f"{args.peer} fwd ms", f"{args.peer} fwd+bwd ms"]
    agreement = ["max abs Δrgb", "mean abs Δrgb", "PSNR dB", "∇means cos / norm", "∇log_scales", "∇opacity", "∇sh"]
    columns = ["N", "size", *timing, *agreement]
    print_header(columns, "rr" + "r" * (len(columns) - 2))
    for spec in args.sizes.split(","):
        n_text, size = spec.split(":")
        n, (w, h) = int(n_text), (int(v) for v in size.split("x"))
        ours = _run("numba", "cpu", n, w, h, args.reps)
        peer = _run(args.peer, device, n, w, h, args.reps)
        cells = [f"{n:,}", size] + [f"{r[k]:.1f}" for r in (ours, peer) for k in ("fwd_ms", "fwd_bwd_ms")]
        print(row(cells + _compare(ours, peer)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
