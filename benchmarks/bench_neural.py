"""Forward time and peak memory of the full-size neural backend, module by module, with random weights.

Networks (the released sizes): MASt3R ViT-L/16 encoder + two ViT-B decoders + ``catmlp+dpt`` heads
(688.6 M parameters), DINOv3 ViT-S/16 (21.6 M), Residual Semantic Fusion (24-d, hidden 64), and the
Splatt3R Gaussian head (two DPTs, 40.4 M). One image pair at ``--size`` (512×384 by default), batch 1.

Modules are timed as the pipeline calls them (``macsplat_cli.pipeline.neural``): the encoder on both
views at once, both decoders, both MASt3R heads, DINOv3 on both views, the fusion on both
descriptor maps, the Gaussian head on both views; then the whole forward pass in one go. Times are
medians of ``--reps`` repetitions after one warm-up. Memory: on CUDA, the peak allocated during the
module minus the allocation before it (``torch.cuda.max_memory_allocated``); on the CPU, the peak
resident set size sampled every millisecond during the module minus the RSS before it (Linux
``/proc``, after ``malloc_trim``; a lower bound where the allocator reuses freed memory), plus the
process's peak RSS overall. Weights: N(0, 0.02) (LayerNorm gains 1), so no
initialisation time is spent.

    python -m benchmarks.bench_neural                           # CPU, fp32, 512x384
    python -m benchmarks.bench_neural --device cuda --dtype bf16 --reps 10
"""

from __future__ import annotations

import argparse
import ctypes
import os
import platform
import statistics
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import torch
from torch import nn

from benchmarks._common import peak_rss_mib, print_header, row
from macsplat_cli.neural import BackboneConfig, GaussianHead, MASt3RBackbone
from macsplat_cli.neural.dinov3 import DINOv3Config, DINOv3Encoder
from macsplat_cli.neural.fusion import FusionConfig, ResidualSemanticFusion

DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


M = TypeVar("M", bound=nn.Module)


def _random(module: M, device: torch.device, dtype: torch.dtype) -> M:
    """``module`` (built on ``meta``) materialised on ``device`` with N(0, 0.02) weights, LayerNorm gains 1."""
    module = module.to_empty(device=device)
    g = torch.Generator(device=device).manual_seed(0)
    with torch.no_grad():
        for name, p in module.named_parameters():
            if isinstance(module.get_submodule(name.rpartition(".")[0]) if "." in name else module, nn.LayerNorm):
                p.fill_(1.0 if name.endswith("weight") else 0.0)
            else:
                p.normal_(0.0, 0.02, generator=g)
        for name, b in module.named_buffers():
            if name.endswith("bias_mask"):  # DINOv3: no key bias
                c = b.numel() // 3
                b.copy_(torch.cat([torch.ones(c), torch.zeros(c), torch.ones(c)]))
            elif name.endswith("periods"):  # DINOv3 RoPE periods, base 100
                n = b.numel()
                b.copy_(torch.tensor([100.0 ** (2 * i / (2 * n)) for i in range(n)]))
    module = module.to(dtype)
    rope: Any = getattr(module, "rope_embed", None)
    if rope is not None:
        rope.periods = rope.periods.float()  # as load_dinov3: RoPE tables in fp32
    return module.eval()


class _PeakRSS:
    """Samples the process RSS every millisecond while active; ``peak`` in bytes."""

    def __init__(self) -> None:
        self.page = os.sysconf("SC_PAGE_SIZE")
        self.peak = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self.page

    def __enter__(self) -> _PeakRSS:
        self.peak = self.rss()
        self._stop.clear()

        def loop() -> None:
            while not self._stop.is_set():
                self.peak = max(self.peak, self.rss())
                time.sleep(0.001)

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        assert self._thread is not None
        self._thread.join()
        self.peak = max(self.peak, self.rss())


def _malloc_trim() -> None:
    """Give freed heap memory back to the OS (glibc), so that the next RSS rise is the module's own."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _measure(fn: Callable[[], Any], device: torch.device, reps: int) -> tuple[float, float, Any]:
    """(median seconds, peak extra memory in MiB, last output) of ``fn`` after one warm-up."""

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    out = fn()  # warm-up
    sync()
    times = []
    for _ in range(reps):
        out = None
        sync()
        t0 = time.perf_counter()
        out = fn()
        sync()
        times.append(time.perf_counter() - t0)
    out = None
    if device.type == "cuda":
        torch.cuda.empty_cache()
        base = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        out = fn()
        sync()
        extra = torch.cuda.max_memory_allocated(device) - base
    else:
        _malloc_trim()
        probe = _PeakRSS()
        base = probe.rss()
        with probe:
            out = fn()
        extra = probe.peak - base
    return statistics.median(times), extra / 2**20, out


def _models(device: torch.device, dtype: torch.dtype) -> tuple[nn.Module, nn.Module, nn.Module, nn.Module]:
    """The released-size backbone, Gaussian head, DINOv3 ViT-S/16 and fusion with random weights."""
    bcfg = BackboneConfig()
    dcfg = DINOv3Config.preset("vits16")
    with torch.device("meta"):
        backbone = MASt3RBackbone(bcfg)
        head = GaussianHead(bcfg.replace(head_type="gaussian_head"))
        dino = DINOv3Encoder(dcfg)
        fusion = ResidualSemanticFusion(FusionConfig(dino_dim=dcfg.embed_dim))
    backbone, head = _random(backbone, device, dtype), _random(head, device, dtype)
    dino, fusion = _random(dino, device, dtype), _random(fusion, device, dtype)
    return backbone, head, dino, fusion


def _time_modules(run: Callable[[str, nn.Module | None, Callable[[], Any]], Any], models: tuple, img: torch.Tensor,
                  rgb: torch.Tensor) -> None:  # fmt: skip
    """Each module as the pipeline calls it, then the whole pass (``run(name, module, fn)`` times one)."""
    backbone, head, dino, fusion = models
    enc1, enc2, pos, grid = run(
        "MASt3R encoder (ViT-L/16, both views)",
        nn.ModuleList([backbone.patch_embed, backbone.enc_blocks, backbone.enc_norm]),
        lambda: backbone.encode(img[:1], img[1:]),
    )
    tok1, tok2 = run(
        "MASt3R decoders (2 × ViT-B, cross-attention)",
        nn.ModuleList([backbone.decoder_embed, backbone.dec_blocks, backbone.dec_blocks2, backbone.dec_norm]),
        lambda: backbone.decode(enc1, enc2, pos),
    )
    v1, v2 = run(
        "MASt3R heads (DPT + local-feature MLP, both views)",
        nn.ModuleList([backbone.downstream_head1, backbone.downstream_head2]),
        lambda: (backbone.predict_view(1, tok1, grid), backbone.predict_view(2, tok2, grid)),
    )
    feats = run("DINOv3 ViT-S/16 (both views)", dino, lambda: dino(img))
    desc = torch.cat([v1.desc, v2.desc])
    run("Residual Semantic Fusion (both views)", fusion, lambda: fusion(desc, feats))
    run("Splatt3R Gaussian head (2 × DPT)", head, lambda: head(v1, v2, rgb[:1], rgb[1:]))
    enc1 = enc2 = tok1 = tok2 = v1 = v2 = feats = desc = None  # type: ignore[assignment]  # freed before the whole pass

    def whole() -> Any:
        a, b = backbone(img[:1], img[1:])
        d = fusion(torch.cat([a.desc, b.desc]), dino(img))
        return head(a, b, rgb[:1], rgb[1:]), d

    run("whole forward pass (all of the above)", nn.ModuleList([backbone, dino, fusion, head]), whole)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--dtype", default="fp32", choices=list(DTYPES))
    ap.add_argument("--reps", type=int, default=3, help="timed repetitions per module (after one warm-up)")
    ap.add_argument("--size", default="512x384", help="WxH of both views (multiples of 16)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: CUDA is not available")
    if args.threads:
        torch.set_num_threads(args.threads)
    device, dtype = torch.device(args.device), DTYPES[args.dtype]
    w, h = (int(v) for v in args.size.lower().split("x"))

    t0 = time.perf_counter()
    models = _models(device, dtype)
    setup_s = time.perf_counter() - t0

    g = torch.Generator().manual_seed(1)
    img = (torch.rand(2, 3, h, w, generator=g) * 2 - 1).to(device, dtype)
    rgb = (img + 1) / 2
    rows: list[tuple[str, float, float, float]] = []

    def run(name: str, module: nn.Module | None, fn: Callable[[], Any]) -> Any:
        with torch.no_grad():
            sec, mib, out = _measure(fn, device, args.reps)
        params = sum(p.numel() for p in module.parameters()) / 1e6 if module is not None else float("nan")
        rows.append((name, params, sec, mib))
        print(f"  {name}: {sec * 1e3:.0f} ms, +{mib:.0f} MiB", flush=True)
        return out

    _time_modules(run, models, img, rgb)
    peak_rss = peak_rss_mib()

    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{platform.processor() or 'CPU'}"
    threads = torch.get_num_threads()
    print()
    print(
        f"{w}x{h} pair, batch 1, {args.dtype}, {device.type} ({where}, {threads} threads), torch {torch.__version__}, "
        f"median of {args.reps} after a warm-up; random weights set up in {setup_s:.1f} s"
    )
    print()
    mem = "peak extra GPU memory MiB" if device.type == "cuda" else "peak extra RSS MiB"
    print_header(["module", "parameters (M)", "forward ms", mem], "lrrr")
    for name, params, sec, mib in rows:
        print(row([name, f"{params:,.1f}", f"{sec * 1e3:,.0f}", f"{mib:,.0f}"]))
    if device.type == "cuda":
        print(f"\npeak GPU memory allocated: {torch.cuda.max_memory_allocated(device) / 2**20:,.0f} MiB")
    print(f"peak process RSS: {peak_rss:,.0f} MiB")


if __name__ == "__main__":
    main()
