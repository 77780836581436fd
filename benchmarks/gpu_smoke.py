"""GPU smoke check: the CUDA paths of the CLI, end to end, with official-layout random weights.

On a machine with an NVIDIA GPU (macsplat's dependencies installed, a CUDA build of PyTorch, and
``onnxruntime-gpu`` for the onnxruntime row), from the repository root:

    python -m benchmarks.gpu_smoke                  # released sizes: ViT-L/ViT-B MASt3R, 512 px (minutes)
    python -m benchmarks.gpu_smoke --tiny           # the tiny layout
    python -m benchmarks.gpu_smoke --steps reconstruct,onnx --keep

It prints one Markdown table (step, result, seconds, peak memory, note) and exits 1 when a step
failed (the tail of each failed step's stderr follows the table). On a machine without a GPU it
prints "no CUDA device: nothing to check" and exits 0; ``--device cpu --tiny`` runs the same steps
on the CPU (how the tests exercise this script).

Nothing is downloaded. In a temporary folder (``--workdir`` to keep it elsewhere; ``--keep``), the
script writes, with the library's own classes:

* random checkpoints in the official layouts: MASt3R ``.pth`` (``{"model", "args"}``, the args string
  from ``BackboneConfig.to_args_string``), a Splatt3R Lightning ``.ckpt`` (``encoder.`` + MASt3R +
  ``gaussian_dpt`` keys), a DINOv3 ``.pth`` (ViT-S/16) and a fusion module (``save_fusion``): the released
  sizes (MASt3R ViT-L/16 encoder + ViT-B decoders, 688.6 M parameters), or ``BackboneConfig.tiny()`` and
  DINOv3 ``tiny`` with ``--tiny``. PyTorch's default initialisation, except MASt3R's last point-map
  convolution (weights × 0.1, bias z = 1), so that the points lie in front of the cameras and the pose
  stage has something to fit;
* a synthetic ScanNet++ tree (``macsplat_cli.datasets.synthetic.write_scannetpp``, undistorted DSLR
  layout, two scenes of 6 frames, 512×384, or 96×64 with ``--tiny``); two of its frames are the
  reconstruct pair.

Then each step runs the real CLI in its own process (``python -m macsplat_cli ...``, shown while it
runs; ``--device D`` and the sizes as above; reconstruct with ``--accept-low-confidence``, since random
weights give no consistent pose):

* ``reconstruct``: ``reconstruct A B --backend neural`` with all four files, fp32;
* ``reconstruct-bf16``: the same with ``--precision bf16``;
* ``export-onnx``: ``export-onnx`` of the same predictor (its parity check runs torch and onnxruntime on
  the CPU);
* ``reconstruct-onnx``: ``reconstruct --weights predictor.onnx --device D``: onnxruntime with the CUDA
  provider (the report's network must name ``CUDAExecutionProvider``: onnxruntime falls back to the CPU
  when its CUDA libraries do not load);
* ``train``: ``train --precision bf16`` for ``--train-steps`` (20) steps on the ScanNet++ tree (512×384, or
  64×48 with ``--tiny``), backbone and DINOv3 frozen (from the random files), Gaussian head and fusion trained
  (bf16 autocast works on the CPU too; ``--precision fp32`` to change it);
* ``train-released``: ``train --recipe released-code`` (the authors' released code's settings: fp32 Adam, batch 1,
  512×512 principal-point crops, 3 targets, the release's MAC form and scale cap) for ``--train-steps`` steps
  (64×64 frames with ``--tiny``);
* ``torchrun``: the same as ``train`` through ``torchrun --standalone --nproc-per-node 1 -m macsplat_cli train`` (run as
  ``python -m torch.distributed.run``: torchrun's own module, with this interpreter);
* ``render``: ``render scene.ply --cameras ... --path 10 --backend gsplat --device cuda`` on the scene of
  ``reconstruct``, when ``import gsplat`` works (else a skipped row); on the CPU ``--backend numba``.

Peak memory. On CUDA: the GPU's used memory as ``nvidia-smi`` reports it, sampled every 100 ms while the
step runs, minus its value before the step; the step's processes alone use the GPU, so this is their
peak footprint: the CUDA context (about 0.5 GiB) and what PyTorch's caching allocator or onnxruntime's
arena reserved, which is more than ``torch.cuda.max_memory_allocated`` (that figure lives inside the
process and cannot be read from here). On the CPU: the peak resident set of the largest process of the
step's tree (``ru_maxrss`` from ``wait4``). Seconds are wall time of the whole process: start-up, loading, work.

The script imports nothing heavy (no torch) until it knows that there is work to do.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shlex
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from benchmarks._gpu_process import Result, gpu_present, nvidia_gpus, run_process

ROOT = Path(__file__).resolve().parents[1]
STEPS = (
    "reconstruct",
    "reconstruct-bf16",
    "export-onnx",
    "reconstruct-onnx",
    "train",
    "train-released",
    "torchrun",
    "render",
)
ALIASES = {"onnx": ("export-onnx", "reconstruct-onnx"), "all": STEPS}
NEEDS = {"reconstruct-onnx": "export-onnx", "render": "reconstruct"}
"""A step that uses another step's output: selecting it selects that step too; its failure skips it."""
NO_CUDA = "no CUDA device: nothing to check"
RENDER_VIEWS = 10


@dataclass(frozen=True)
class Sizes:
    """Image and network sizes of one run.

    Args:
        image: the synthetic frames (W, H); the reconstruct pair is two of them.
        reconstruct: ``--size`` of reconstruct (long side, a multiple of 16).
        train: ``--size`` of train (W, H).
    """

    image: tuple[int, int]
    reconstruct: int
    train: tuple[int, int]


FULL = Sizes(image=(512, 384), reconstruct=512, train=(512, 384))
TINY = Sizes(image=(96, 64), reconstruct=96, train=(64, 48))


# ============================================================================================= inputs
def write_checkpoints(folder: Path, *, tiny: bool) -> dict[str, Path]:
    """Random weights in the official layouts (module docstring): ``mast3r``, ``splatt3r``, ``dino``, ``fusion``."""
    import argparse as ap
    import math

    import torch

    from macsplat_cli.neural import BackboneConfig, GaussianHead, MASt3RBackbone
    from macsplat_cli.neural.config import GaussianHeadConfig
    from macsplat_cli.neural.dinov3 import DINOv3Config, DINOv3Encoder
    from macsplat_cli.neural.fusion import FusionConfig, ResidualSemanticFusion, save_fusion

    folder.mkdir(parents=True, exist_ok=True)
    cfg = BackboneConfig.tiny() if tiny else BackboneConfig()
    names = {"mast3r": "mast3r.pth", "splatt3r": "splatt3r.ckpt", "dino": "dinov3.pth", "fusion": "fusion.pth"}
    files = {k: folder / n for k, n in names.items()}
    torch.manual_seed(0)
    backbone = MASt3RBackbone(cfg).state_dict()
    with torch.no_grad():  # points in front of both cameras (z ≈ e − 1), else the pose stage has nothing to fit
        for i in (1, 2):
            backbone[f"downstream_head{i}.dpt.head.4.weight"].mul_(0.1)
            backbone[f"downstream_head{i}.dpt.head.4.bias"].copy_(torch.tensor([0.0, 0.0, 1.0, 0.0]))
    torch.save({"model": backbone, "args": ap.Namespace(model=cfg.to_args_string())}, files["mast3r"])
    # Splatt3R builds MASt3R with its Gaussian head and omits desc_conf_mode (upstream default (exp, 1, inf));
    # the backbone keys are the same, so the same tensors stand for its frozen encoder.
    gcfg = cfg.replace(head_type="gaussian_head", desc_conf_mode=("exp", 1.0, math.inf))
    head = GaussianHead(gcfg, GaussianHeadConfig()).state_dict()
    state = {"encoder." + k: v for k, v in {**backbone, **head}.items()}
    torch.save({"state_dict": state, "epoch": 19, "global_step": 1200}, files["splatt3r"])
    del backbone, head, state
    dcfg = DINOv3Config.preset("tiny" if tiny else "vits16")
    torch.save(DINOv3Encoder(dcfg).state_dict(), files["dino"])
    fusion = ResidualSemanticFusion(FusionConfig(desc_dim=cfg.local_feat_dim, dino_dim=dcfg.embed_dim))
    with torch.no_grad():  # as after training: a non-zero last layer, so the fusion changes the descriptors
        last = fusion.layers[-1]
        assert isinstance(last, torch.nn.Linear)
        last.weight.normal_(0.0, 0.02)
    save_fusion(fusion, files["fusion"])
    return files


def write_data(root: Path, size: tuple[int, int]) -> tuple[Path, Path, Path]:
    """A synthetic ScanNet++ tree (2 scenes × 6 frames); returns ``(root, frame A, frame B)`` for reconstruct."""
    from macsplat_cli.datasets import synthetic as syn

    syn.write_scannetpp(root, frames=6, size=size)
    images = sorted((root / "data" / "room" / "dslr" / "resized_undistorted_images").iterdir())
    return root, images[0], images[2]


# ============================================================================================= the steps
@dataclass
class Plan:
    """Everything the steps need."""

    device: str
    tiny: bool
    sizes: Sizes
    work: Path
    files: dict[str, Path]
    data: Path
    pair: tuple[Path, Path]
    train_steps: int
    train_precision: str
    timeout: float
    gsplat: bool

    def cli(self, *args: object) -> list[str]:
        return [sys.executable, "-m", "macsplat_cli", *map(str, args)]

    @property
    def neural_files(self) -> list[object]:
        f = self.files
        return ["--weights", f["mast3r"], "--gaussian-head", f["splatt3r"], "--dino", f["dino"],
                "--fusion", f["fusion"]]  # fmt: skip

    def reconstruct(self, out: str, *extra: object) -> list[str]:
        return self.cli(
            "reconstruct", *self.pair, "-o", Path(out, "scene.ply"), "--backend", "neural", *extra,
            "--device", self.device, "--size", self.sizes.reconstruct, "--accept-low-confidence",
            "--report", Path(out, "report.json"), "-q",
        )  # fmt: skip

    def train_args(self, out: str) -> list[object]:
        w, h = self.sizes.train
        f = self.files
        return [
            "train", "--data", self.data, "--out", out, "--weights", f["mast3r"], "--gaussian-head",
            f["splatt3r"], "--dino", f["dino"], "--steps", self.train_steps, "--batch", 2, "--warmup", 2,
            "--val-every", 0, "--ckpt-every", self.train_steps, "--precision", self.train_precision,
            "--device", self.device, "--size", f"{w}x{h}", "--workers", 0 if self.tiny else 2, "-q",
        ]  # fmt: skip

    def command(self, step: str) -> list[str]:
        if step == "reconstruct":
            return self.reconstruct("reconstruct", *self.neural_files)
        if step == "reconstruct-bf16":
            return self.reconstruct("reconstruct-bf16", *self.neural_files, "--precision", "bf16")
        if step == "export-onnx":
            w, h = self.sizes.image
            return self.cli("export-onnx", *self.neural_files, "-o", Path("onnx", "predictor.onnx"),
                            "--size", f"{w}x{h}", "-q")  # fmt: skip
        if step == "reconstruct-onnx":
            return self.reconstruct("reconstruct-onnx", "--weights", Path("onnx", "predictor.onnx"))
        if step == "train":
            return self.cli(*self.train_args("train"))
        if step == "train-released":
            f = self.files
            size = ["--size", "64x64"] if self.tiny else []  # else the recipe's 512x512
            return self.cli("train", "--data", self.data, "--out", step, "--recipe", "released-code", "--weights",
                            f["mast3r"], "--gaussian-head", f["splatt3r"], "--dino", f["dino"], "--steps",
                            self.train_steps, "--val-every", 0, "--ckpt-every", self.train_steps, "--device",
                            self.device, *size, "--workers", 0 if self.tiny else 2, "-q")  # fmt: skip
        if step == "torchrun":
            return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "1",
                    "-m", "macsplat_cli", *map(str, self.train_args("torchrun"))]  # fmt: skip
        if step == "render":
            scene = Path("reconstruct")
            backend = "gsplat" if self.device == "cuda" else "numba"
            return self.cli("render", scene / "scene.ply", "--cameras", scene / "scene.cameras.json", "--path",
                            RENDER_VIEWS, "-o", "render", "--backend", backend, "--device", self.device,
                            "-q")  # fmt: skip
        raise ValueError(f"unknown step {step!r}")

    def check(self, step: str) -> Callable[[], str]:
        """What a step that exited 0 must have written (raises AssertionError), and the row's note."""

        def reconstruct() -> str:
            import json

            r = json.loads((self.work / step / "report.json").read_text())
            n = r["gaussians_written"]
            assert n > 0 and (self.work / step / "scene.ply").is_file(), "no Gaussians were written"
            network = str(r["backends"].get("network", ""))
            if step == "reconstruct-onnx":
                want = "CUDAExecutionProvider" if self.device == "cuda" else "CPUExecutionProvider"
                assert want in network, f"onnxruntime did not use {want}: {network}"
                return f"{n:,} Gaussians; {want}"
            return f"{n:,} Gaussians"

        def export() -> str:
            onnx = self.work / "onnx" / "predictor.onnx"
            assert onnx.is_file(), f"{onnx.name} was not written"
            data = onnx.with_name(onnx.name + ".data")
            size = onnx.stat().st_size + (data.stat().st_size if data.exists() else 0)
            return f"{size / 2**20:,.0f} MiB" + (" (external data)" if data.exists() else "")

        def train() -> str:
            import csv

            run = self.work / step
            assert (run / "last.pt").is_file(), "no last.pt"
            with open(run / "metrics.csv", newline="") as f:
                rows = [r for r in csv.DictReader(f) if r.get("kind") == "train"]
            last = int(rows[-1]["step"]) if rows else 0
            assert last == self.train_steps, f"metrics.csv ends at step {last}, not {self.train_steps}"
            precision = "fp32 released-code" if step == "train-released" else self.train_precision
            return f"{self.train_steps} steps {precision}, loss {float(rows[-1]['loss']):.3g}"

        def render() -> str:
            frames = sorted((self.work / "render").glob("*.png"))
            assert len(frames) == RENDER_VIEWS, f"{len(frames)} of {RENDER_VIEWS} views written"
            return f"{len(frames)} views, " + ("gsplat" if self.device == "cuda" else "numba (gsplat needs CUDA)")

        checks = {"export-onnx": export, "train": train, "train-released": train, "torchrun": train, "render": render}
        return checks.get(step, reconstruct)


def select_steps(spec: str) -> list[str]:
    """``--steps``: step names or aliases (``onnx``, ``all``), comma-separated, with the steps they need, in order.

    Raises:
        ValueError: an unknown name.
    """
    chosen: set[str] = set()
    for name in (s.strip() for s in spec.split(",")):
        if not name:
            continue
        if name in ALIASES:
            chosen.update(ALIASES[name])
        elif name in STEPS:
            chosen.add(name)
        else:
            raise ValueError(f"unknown step {name!r} (one of {', '.join((*STEPS, *ALIASES))})")
    for step in list(chosen):
        while step in NEEDS:
            step = NEEDS[step]
            chosen.add(step)
    return [s for s in STEPS if s in chosen]


# ============================================================================================= report
def table(results: Sequence[Result], *, gpu: bool) -> str:
    """The Markdown table of the results."""
    memory = "peak GPU MiB" if gpu else "peak RSS MiB"
    lines = [f"| step | result | seconds | {memory} | note |", "|---|---|---:|---:|---|"]
    for r in results:
        sec = f"{r.seconds:.1f}" if r.seconds is not None else "-"
        mib = f"{r.peak_mib:,.0f}" if r.peak_mib is not None else "-"
        note = r.note.replace("|", "\\|")
        lines.append(f"| {r.step} | {r.status} | {sec} | {mib} | {note} |")
    return "\n".join(lines)


def exit_code(results: Sequence[Result]) -> int:
    """1 when any step failed, else 0 (skipped steps do not fail the check)."""
    return int(any(r.status == "failed" for r in results))


def environment(device: str) -> str:
    """One line on what runs the steps (torch, its CUDA device, onnxruntime and its providers, gsplat)."""
    import torch

    parts = [f"Python {sys.version.split()[0]}", f"torch {torch.__version__}"]
    if device == "cuda":
        parts.append(f"{torch.cuda.get_device_name()} (CUDA {torch.version.cuda})")
    try:
        import onnxruntime as ort

        parts.append(f"onnxruntime {ort.__version__} ({', '.join(ort.get_available_providers())})")
    except ImportError:
        parts.append("no onnxruntime")
    if importlib.util.find_spec("gsplat") is not None:
        from importlib.metadata import version

        parts.append(f"gsplat {version('gsplat')}")
    return ", ".join(parts)


def shown(argv: Sequence[str]) -> str:
    """A command line as a person would type it (``python`` for this interpreter)."""
    return shlex.join(["python" if a == sys.executable else a for a in argv])


# ============================================================================================= main
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description="GPU smoke check: neural reconstruct (torch and onnxruntime-CUDA), bf16 train, torchrun and the "
        "gsplat rasterizer on CUDA with official-layout random weights; one Markdown table; exit 1 on a failure.",
    )
    p.add_argument(
        "--device", choices=("cuda", "cpu"), default="cuda",
        help="cuda (default; where there is no GPU: a message and exit 0) or cpu (tests this script)",
    )  # fmt: skip
    p.add_argument("--tiny", action="store_true", help="the tiny layout and 96x64 images instead of the released sizes")
    p.add_argument("--steps", default="all",
                   help=f"comma-separated: {', '.join(STEPS)}, onnx (both onnx steps), all [default: all]")  # fmt: skip
    p.add_argument("--train-steps", type=int, default=20, help="optimiser steps of train and torchrun [default: 20]")
    p.add_argument("--precision", choices=("bf16", "fp32"), default="bf16",
                   help="precision of train and torchrun [default: bf16]")  # fmt: skip
    p.add_argument("--timeout", type=float, default=600.0, help="seconds before a step is killed [default: 600]")
    p.add_argument("--workdir", type=Path, default=None, help="work folder (kept); default: a temporary one")
    p.add_argument("--keep", action="store_true", help="keep the temporary work folder")
    args = p.parse_args(argv)
    try:
        args.selected = select_steps(args.steps)
    except ValueError as e:
        p.error(str(e))
    if not args.selected:
        p.error("--steps selects no step")
    if args.train_steps < 1:
        p.error("--train-steps must be at least 1")
    if args.timeout <= 0:
        p.error("--timeout must be positive")
    return args


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Prepare the inputs, run the selected steps, print the table; the exit code."""
    if args.device == "cuda":
        if not gpu_present():
            print(NO_CUDA)
            return 0
        import torch

        if not torch.cuda.is_available():
            gpus = nvidia_gpus()
            print(f"error: {gpus[0] if gpus else 'an NVIDIA GPU'} is attached but torch {torch.__version__} sees no "
                  "CUDA device (a CPU build, or a driver it cannot use): nothing could be checked")  # fmt: skip
            return 1
    gpu = args.device == "cuda"
    tmp = None
    if args.workdir is not None:
        work = args.workdir.resolve()
        work.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.mkdtemp(prefix="macsplat-gpu-smoke-")
        work = Path(tmp)
    try:
        return _run_in(args, work, gpu)
    finally:
        if tmp is not None and not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp is not None:
            _progress(f"work folder kept: {tmp}")


def _run_in(args: argparse.Namespace, work: Path, gpu: bool) -> int:
    sizes = TINY if args.tiny else FULL
    _progress(f"macsplat GPU smoke check, device {args.device}, {'tiny' if args.tiny else 'full'} sizes, in {work}")
    results: list[Result] = []
    t0 = time.perf_counter()
    try:
        files = write_checkpoints(work / "weights", tiny=args.tiny)
        data, a, b = write_data(work / "scannetpp", sizes.image)
    except Exception as e:  # noqa: BLE001 - any failure here is the smoke check's finding, reported in the table
        results.append(Result("prepare", "failed", time.perf_counter() - t0, None, f"{type(e).__name__}: {e}"))
        results += [Result(s, "skipped", note="needs prepare") for s in args.selected]
        print(table(results, gpu=gpu))
        return 1
    mib = sum(f.stat().st_size for f in files.values()) / 2**20
    results.append(Result("prepare", "ok", time.perf_counter() - t0, None,
                          f"random weights {mib:,.0f} MiB, ScanNet++ {sizes.image[0]}x{sizes.image[1]}"))  # fmt: skip
    rel = {k: f.relative_to(work) for k, f in files.items()}  # the steps run in ``work``: short command lines
    plan = Plan(args.device, args.tiny, sizes, work, rel, data.relative_to(work), (a.relative_to(work),
                b.relative_to(work)), args.train_steps, args.precision, args.timeout,
                importlib.util.find_spec("gsplat") is not None)  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    env.setdefault("PYTHONUNBUFFERED", "1")
    status: dict[str, str] = {}
    for i, step in enumerate(args.selected, 1):
        need = NEEDS.get(step)
        if need is not None and status.get(need) != "ok":
            results.append(Result(step, "skipped", note=f"needs {need}"))
        elif step == "render" and gpu and not plan.gsplat:
            results.append(Result(step, "skipped", note="gsplat is not installed (import gsplat fails)"))
        else:
            argv = plan.command(step)
            _progress(f"[{i}/{len(args.selected)}] {step}: {shown(argv)}")
            results.append(run_process(step, argv, cwd=work, env=env, timeout=args.timeout, gpu=gpu,
                                       logs=work / "logs", check=plan.check(step)))  # fmt: skip
        status[step] = results[-1].status
        _progress(f"    {results[-1].status} {results[-1].note}")
    print(f"{environment(args.device)}; {'tiny' if args.tiny else 'released'} sizes\n")
    print(table(results, gpu=gpu))
    for r in results:
        if r.status == "failed" and r.stderr_tail:
            print(f"\n{r.step} (stderr, last lines):\n" + "\n".join(f"    {ln}" for ln in r.stderr_tail))
    return exit_code(results)


def main(argv: Sequence[str] | None = None) -> int:
    return run(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
