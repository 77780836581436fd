"""The projection step against gsplat's plain-PyTorch reference, forward + backward, on the CPU.

gsplat (Apache-2.0) ships a pure-PyTorch twin of its CUDA kernels in ``gsplat.cuda._torch_impl`` (private API); its
projection runs on a CPU, its rasterisation does not (``_rasterize_to_pixels`` calls a CUDA kernel), so the
projection is the peer. Same scene as ``bench_render.py`` (SH degree 0); the loss sums every output. Ours does more:
it also culls by opacity and screen support and sorts by depth. Ours twice: the plain-PyTorch twin
(``projection.py``) and the fused Numba kernel the renderer uses (``fused.py``, issue 40). Without gsplat
(``pip install --no-deps gsplat jaxtyping``; it compiles nothing until CUDA is used) only ours are timed.

    python -m benchmarks.projection_peer [--sizes 100000,1000000] [--reps 5]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time

from benchmarks._common import print_header, render_scene_params, row


def _timed(fn, params, reps: int) -> float:  # noqa: ANN001
    fn().backward()
    times = []
    for _ in range(reps):
        for p in params:
            p.grad = None
        t0 = time.perf_counter()
        fn().backward()
        times.append(time.perf_counter() - t0)
    return 1e3 * sorted(times)[reps // 2]


def _compare(n: int, w: int, h: int, K, V, reps: int, peer: bool) -> tuple[float, float, float]:  # noqa: ANN001
    """(gsplat ms or NaN, macsplat twin ms, macsplat fused ms) for ``n`` Gaussians."""
    import torch

    from macsplat_cli.render.fused import project_gaussians_fused
    from macsplat_cli.render.projection import project_gaussians

    _, params = render_scene_params(n)
    means, logs, quats, opl, sh = params
    for t in params:
        t.requires_grad_(True)

    def theirs() -> torch.Tensor:
        from gsplat.cuda import _torch_impl as gs

        covars, _ = gs._quat_scale_to_covar_preci(quats, torch.exp(logs), compute_covar=True, compute_preci=False,
                                                  triu=False)  # fmt: skip
        _, means2d, depths, conics, _ = gs._fully_fused_projection(means, covars, V[None], K[None], w, h)
        colors = (sh[:, 0, :] * 0.28209479177387814 + 0.5).clamp_min(0)
        return means2d.sum() + conics.sum() + depths.sum() + colors.sum() + torch.sigmoid(opl).sum()

    def ours(project) -> torch.Tensor:  # noqa: ANN001
        pr = project(means, logs, quats, opl, sh, V, K, w, h)
        return pr.means2d.sum() + pr.conics.sum() + pr.depths.sum() + pr.colors.sum() + pr.opacities.sum()

    peer_ms = _timed(theirs, params, reps) if peer else float("nan")
    twin = _timed(lambda: ours(project_gaussians), params, reps)
    return peer_ms, twin, _timed(lambda: ours(project_gaussians_fused), params, reps)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="100000,1000000", help="numbers of Gaussians, comma-separated")
    p.add_argument("--reps", type=int, default=5)
    args = p.parse_args(argv)
    peer = importlib.util.find_spec("gsplat") is not None
    if not peer:
        print("gsplat is not installed (pip install --no-deps gsplat jaxtyping): ours only\n")
    import torch

    w = h = 256
    K = torch.tensor([[float(w), 0.0, w / 2], [0.0, float(w), h / 2], [0.0, 0.0, 1.0]])
    V = torch.eye(4)
    print(f"projection forward+backward, {w}x{h}, {torch.get_num_threads()} torch threads, median of {args.reps}\n")
    print_header(["Gaussians", "gsplat _torch_impl ms", "macsplat twin ms", "macsplat fused ms", "fused ÷ gsplat",
                  "fused ÷ twin"], "rrrrrr")  # fmt: skip
    for n in (int(v) for v in args.sizes.split(",")):
        a, b, c = _compare(n, w, h, K, V, args.reps, peer)
        print(row([f"{n:,}", f"{a:.1f}", f"{b:.1f}", f"{c:.1f}", f"{c / a:.2f}", f"{c / b:.2f}"]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
