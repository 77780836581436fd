"""torch against onnxruntime: latency and peak memory of the whole predictor, by precision and thread count.

The predictor is the released architecture with random weights (MASt3R ViT-L/16 encoder + two ViT-B
decoders + heads, 688.6 M parameters, and the Splatt3R Gaussian head, 40.4 M; ``--model tiny`` for a
smoke run). It is exported once with ``macsplat_cli.neural.onnx_export.export_onnx`` (fp32, dynamic size,
its parity check included; int8 = onnxruntime's dynamic quantisation; fp16 with ``--fp16``) into
``--workdir`` (re-used when present), then every (engine, precision, threads) cell runs in a fresh
process, so that its peak resident memory (``ru_maxrss``) is its own: loading the weights, a warm-up,
and ``--reps`` timed forward passes on one 512×384 pair (median reported). ORT runs alone in its
process, so its threads may spin (its default); torch runs under ``inference_mode``.

Precisions: torch fp32; torch bf16 (autocast on the CPU); torch int8 (``torch.ao`` dynamic quantisation
of every ``nn.Linear``); ORT fp32; ORT int8 (the exported int8 file); ORT fp16 (``--fp16``: a GPU format,
timed here for completeness). ORT has no bf16 CPU kernels, so there is no ORT bf16 cell. The error
column is each cell's largest output error against torch fp32 on the same pair, relative to the
output's range (as the export's parity check).

    python -m benchmarks.bench_onnx                             # full size, 1 and 2 threads
    python -m benchmarks.bench_onnx --model tiny --reps 3       # a minute
    python -m benchmarks.bench_onnx --provider cuda             # on a GPU: torch CUDA vs ORT-CUDA
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

CELLS = [
    ("torch", "fp32"),
    ("torch", "bf16"),
    ("torch", "int8"),
    ("onnxruntime", "fp32"),
    ("onnxruntime", "int8"),
]


def build_predictor(model: str) -> Any:
    """The predictor with N(0, 0.02) weights (LayerNorm gains 1), seeded."""
    from torch import nn

    from macsplat_cli.neural import BackboneConfig, GaussianHead, MASt3RBackbone
    from macsplat_cli.neural.predictor import PairPredictor

    cfg = BackboneConfig.tiny() if model == "tiny" else BackboneConfig()
    cfg = cfg.replace(head_type="gaussian_head")
    torch.manual_seed(0)
    with torch.device("meta"):
        backbone, head = MASt3RBackbone(cfg), GaussianHead(cfg)
    pred = PairPredictor(backbone, head).to_empty(device="cpu")
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, p in pred.named_parameters():
            owner = pred.get_submodule(name.rpartition(".")[0]) if "." in name else pred
            if isinstance(owner, nn.LayerNorm):
                p.fill_(1.0 if name.endswith("weight") else 0.0)
            else:
                p.normal_(0.0, 0.02, generator=g)
    return pred.eval()


def export(model: str, workdir: Path, size: tuple[int, int], fp16: bool) -> dict[str, Path]:
    from macsplat_cli.datasets.synthetic.sample import sample_pair
    from macsplat_cli.neural.onnx_export import ExportConfig, export_onnx

    files = {"fp32": workdir / f"{model}_fp32.onnx", "int8": workdir / f"{model}_int8.onnx"}
    if fp16:
        files["fp16"] = workdir / f"{model}_fp16.onnx"
    pred = None
    for precision, path in files.items():
        if path.exists():
            continue
        pred = pred if pred is not None else build_predictor(model)
        cfg = ExportConfig(size=size, fp16=precision == "fp16", quantize="int8" if precision == "int8" else None)
        t0 = time.perf_counter()
        r = export_onnx(pred, path, cfg, sample=sample_pair(size))
        worst = r.parity.worst
        print(f"exported {path.name}: {r.bytes / 1e6:,.0f} MB in {time.perf_counter() - t0:.0f} s "
              f"({', '.join(f'{k} {v:.0f} s' for k, v in r.seconds.items())}); parity worst {worst['output']} "
              f"{worst['max_rel']:.2e}", flush=True)  # fmt: skip
    return files


# ============================================================================================= one cell
def _cell(args: argparse.Namespace) -> dict[str, Any]:
    """Run in a fresh process: load, warm up, time; peak RSS of this process."""
    import numpy as np

    from macsplat_cli.datasets.synthetic.sample import sample_pair
    from macsplat_cli.neural.onnx_format import compare_outputs

    torch.set_num_threads(args.threads)
    imgs = sample_pair(tuple(args.size))
    ref = [np.load(args.reference)[f"arr_{i}"] for i in range(len(np.load(args.reference).files))]
    t0 = time.perf_counter()
    if args.engine == "torch":
        pred = build_predictor(args.model)
        if args.precision == "int8":
            from torch.ao.quantization import quantize_dynamic

            pred = quantize_dynamic(pred, {torch.nn.Linear}, dtype=torch.qint8)

        def run() -> list[np.ndarray]:
            with torch.inference_mode(), torch.autocast("cpu", torch.bfloat16, enabled=args.precision == "bf16"):
                return [o.float().numpy() for o in pred(*imgs)]

        names = pred.output_names
    else:
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = args.threads
        so.inter_op_num_threads = 1
        providers = ["CUDAExecutionProvider"] if args.provider == "cuda" else ["CPUExecutionProvider"]
        sess = ort.InferenceSession(args.onnx, sess_options=so, providers=providers)
        feeds = {"img0": imgs[0].numpy(), "img1": imgs[1].numpy()}
        names = [o.name for o in sess.get_outputs()]

        def run() -> list[np.ndarray]:
            return sess.run(None, feeds)

    load_s = time.perf_counter() - t0
    out = run()  # warm-up
    times = []
    for _ in range(args.reps):
        t0 = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t0)
    ref_t = [torch.from_numpy(r) for r in ref]
    rows = compare_outputs(names, out, tuple(ref_t), 1.0)
    worst = max(rows, key=lambda r: r["max_rel"])
    return {
        "median_s": statistics.median(times), "min_s": min(times), "load_s": load_s,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "worst_output": worst["output"], "worst_rel": worst["max_rel"],
    }  # fmt: skip


def _reference(model: str, size: tuple[int, int], path: Path) -> None:
    import numpy as np

    from macsplat_cli.datasets.synthetic.sample import sample_pair

    if path.exists():
        return
    pred = build_predictor(model)
    with torch.inference_mode():
        out = pred(*sample_pair(size))
    np.savez(path, *[o.numpy() for o in out])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", choices=("full", "tiny"), default="full")
    ap.add_argument("--size", default="512x384")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--fp16", action="store_true", help="also export and time an fp16 file")
    ap.add_argument("--provider", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/macsplat_bench_onnx"))
    ap.add_argument("--json", type=Path, help="also write the rows here")
    # internal: one cell in a child process
    ap.add_argument("--cell", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--engine", help=argparse.SUPPRESS)
    ap.add_argument("--precision", help=argparse.SUPPRESS)
    ap.add_argument("--onnx", help=argparse.SUPPRESS)
    ap.add_argument("--reference", help=argparse.SUPPRESS)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    args.size = (w, h)
    if args.cell:
        args.threads = int(args.threads)
        print(json.dumps(_cell(args)))
        return

    args.workdir.mkdir(parents=True, exist_ok=True)
    files = export(args.model, args.workdir, (w, h), args.fp16)
    ref = args.workdir / f"{args.model}_{w}x{h}_reference.npz"
    _reference(args.model, (w, h), ref)
    cells = CELLS + ([("onnxruntime", "fp16")] if args.fp16 else [])
    rows = []
    print(f"\n{args.model} predictor, {w}x{h} pair, batch 1; {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores; torch {torch.__version__}; median of {args.reps} after a warm-up\n")  # fmt: skip
    print("| engine | precision | threads | median s | peak RSS GB | load s | worst output error (rel. to range) |")
    print("|---|---|---:|---:|---:|---:|---|")
    for threads in (int(t) for t in args.threads.split(",")):
        for engine, precision in cells:
            cmd = [sys.executable, "-m", "benchmarks.bench_onnx", "--cell", "--model", args.model, "--size", f"{w}x{h}",
                   "--threads", str(threads), "--reps", str(args.reps), "--engine", engine, "--precision", precision,
                   "--reference", str(ref), "--provider", args.provider]  # fmt: skip
            if engine == "onnxruntime":
                cmd += ["--onnx", str(files[precision])]
            env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
            p = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if p.returncode != 0:
                line = (p.stderr.strip().splitlines() or ["?"])[-1][:100]
                print(f"| {engine} | {precision} | {threads} | failed: {line} | | | |", flush=True)
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            rows.append({"engine": engine, "precision": precision, "threads": threads, **r})
            print(f"| {engine} | {precision} | {threads} | {r['median_s']:.2f} | {r['peak_rss_gb']:.2f} | "
                  f"{r['load_s']:.1f} | {r['worst_output']} {r['worst_rel']:.1e} |", flush=True)  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
