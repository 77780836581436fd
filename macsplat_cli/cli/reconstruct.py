"""``macsplat reconstruct``: two photos → a 3DGS PLY, the cameras, novel views, a report."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from . import app
from ._common import QuietOpt, VerboseOpt, command_context, err_console, out_console

logger = logging.getLogger("macsplat_cli.cli.reconstruct")


@app.command("reconstruct")
def reconstruct_command(
    ctx: typer.Context,
    image_a: Annotated[Path, typer.Argument(metavar="A", help="First photo (defines the world frame).")],
    image_b: Annotated[Path, typer.Argument(metavar="B", help="Second photo.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="The Gaussian scene to write (.ply).")],
    cameras: Annotated[
        Path | None,
        typer.Option("--cameras", help="Where to write the estimated cameras [default: <stem>.cameras.json]."),
    ] = None,
    renders: Annotated[
        Path | None, typer.Option("--renders", help="Folder for novel views along the path between the cameras.")
    ] = None,
    num_renders: Annotated[int, typer.Option("--num-renders", min=2, help="Number of novel views.")] = 10,
    video: Annotated[Path | None, typer.Option("--video", help="Also write the novel views as .mp4 or .gif.")] = None,
    report: Annotated[Path | None, typer.Option("--report", help="Write the run report (JSON) here.")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the report as JSON on stdout.")] = False,
    size: Annotated[
        int, typer.Option("--size", min=64, help="Long side of the working images (multiple of 16).")
    ] = 512,
    intrinsics: Annotated[
        Path | None, typer.Option("--intrinsics", help="Camera file (cameras schema) with the photos' intrinsics.")
    ] = None,
    focal: Annotated[
        float | None, typer.Option("--focal", help="Focal length in pixels of the original photos.")
    ] = None,
    conf_threshold: Annotated[
        float | None,
        typer.Option(
            "--conf-threshold",
            help="τ: keep matches whose joint confidence c0·c1 exceeds it [default: 0.04; 1 with --backend neural].",
        ),
    ] = None,
    refine: Annotated[
        str,
        typer.Option(
            "--refine",
            metavar="STEPS",
            help="Refine the Gaussians on the two photos (+ MAC loss) for up to STEPS steps; 'auto' = 50. 0 = off.",
        ),
    ] = "0",
    refine_scale: Annotated[
        int, typer.Option("--refine-scale", min=1, max=4, help="Refine at 1/N resolution (2: ~4x faster per step).")
    ] = 2,
    no_mac: Annotated[bool, typer.Option("--no-mac", help="Refine without the MAC loss (ablation).")] = False,
    lpips_weights: Annotated[
        Path | None,
        typer.Option(
            "--lpips-weights",
            metavar="PATH",
            help="Add LPIPS to the refinement's loss: a folder with torchvision's vgg16-*.pth and LPIPS v0.1 vgg.pth.",
        ),
    ] = None,
    backend: Annotated[
        str,
        typer.Option(
            "--backend",
            metavar="classical|neural",
            help="classical: no learned weights (default); neural: MASt3R point maps and descriptors (--weights).",
        ),
    ] = "classical",
    weights: Annotated[
        Path | None,
        typer.Option("--weights", help="MASt3R checkpoint (.pth or Hugging Face folder) for --backend neural."),
    ] = None,
    dino: Annotated[
        Path | None, typer.Option("--dino", help="DINOv3 weights for semantic fusion of the descriptors (neural).")
    ] = None,
    fusion: Annotated[
        Path | None, typer.Option("--fusion", help="Residual Semantic Fusion weights (with --dino; neural).")
    ] = None,
    gaussian_head: Annotated[
        Path | None,
        typer.Option(
            "--gaussian-head",
            help="Splatt3R checkpoint (.ckpt): Gaussians from its head; alone it also provides the backbone (neural).",
        ),
    ] = None,
    device: Annotated[str, typer.Option("--device", metavar="cpu|cuda", help="Where the neural backend runs.")] = "cpu",
    precision: Annotated[
        str, typer.Option("--precision", metavar="fp32|bf16", help="Neural backend arithmetic (bf16: faster).")
    ] = "fp32",
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Reconstruct a Gaussian splat scene from two photos.

    Writes the scene (standard 3DGS PLY), the two estimated cameras (world = first camera;
    relative scale, baseline 1, with the classical backend; metres with the neural one), and
    optionally novel views, a video and a JSON report. The default backend needs no learned
    weights; [bold]--backend neural[/] uses MASt3R (user-supplied checkpoint, see models/).

    [bold]Examples[/]

      macsplat reconstruct a.jpg b.jpg -o scene.ply --renders views/ --video path.mp4

      macsplat reconstruct a.jpg b.jpg -o scene.ply --backend neural --weights mast3r.pth
    """
    with command_context(ctx, verbose, quiet) as state:
        _reconstruct(
            images=[image_a, image_b], output=output, cameras=cameras, renders=renders, num_renders=num_renders,
            video=video, report=report, json_out=json_out, size=size, intrinsics=intrinsics, focal=focal,
            conf_threshold=conf_threshold, refine_steps=_refine_steps(refine), refine_scale=refine_scale,
            use_mac=not no_mac, quiet=state.quiet, lpips_weights=lpips_weights,
            neural=_neural_options(backend, weights, dino, fusion, gaussian_head, device, precision),
        )  # fmt: skip


def _neural_options(
    backend: str, weights: Path | None, dino: Path | None, fusion: Path | None, gaussian_head: Path | None,
    device: str, precision: str = "fp32",
) -> dict[str, Any] | None:  # fmt: skip
    """The neural backend's files and device, or None for the classical backend (usage checked here)."""
    from ..errors import InputError

    name = backend.strip().lower()
    if name not in ("classical", "neural"):
        raise InputError(f"--backend {backend!r}: use classical or neural")
    dev = device.strip().lower()
    if dev not in ("cpu", "cuda"):
        raise InputError(f"--device {device!r}: use cpu or cuda")
    if precision not in ("fp32", "bf16"):
        raise InputError(f"--precision {precision!r}: use fp32 or bf16")
    given = {"--weights": weights, "--dino": dino, "--fusion": fusion, "--gaussian-head": gaussian_head}
    if name == "classical":
        extra = [opt for opt, v in given.items() if v is not None] + (["--device"] if dev != "cpu" else [])
        extra += ["--precision"] if precision != "fp32" else []
        if extra:
            raise InputError(f"{', '.join(extra)} only apply to --backend neural")
        return None
    from ..pipeline.neural import MISSING_WEIGHTS_HELP, check_fusion_files, resolve_device

    if weights is None and gaussian_head is None:
        raise InputError(MISSING_WEIGHTS_HELP)
    check_fusion_files(dino, fusion)
    resolve_device(dev)
    files = {"weights": weights, "dino": dino, "fusion": fusion, "gaussian_head": gaussian_head, "device": dev}
    return {**files, "precision": precision}


def _refine_steps(text: str) -> int:
    from ..errors import InputError
    from ..refine import RefineConfig

    if text.strip().lower() == "auto":
        return RefineConfig().steps
    try:
        steps = int(text)
    except ValueError:
        steps = -1
    if steps < 0:
        raise InputError(f"--refine {text!r}: give a number of steps (0 = off) or 'auto'")
    return steps


def _check_outputs(output: Path, cameras: Path, renders: Path | None, video: Path | None, report: Path | None) -> None:
    from .._atomic import check_writable
    from ..errors import InputError
    from ..images import VIDEO_FORMATS

    if output.suffix.lower() != ".ply":
        raise InputError(f"{output}: the scene is written as a .ply file")
    for p in (output, cameras, video, report):
        if p is not None:
            check_writable(p)
    if video is not None and video.suffix.lower() not in VIDEO_FORMATS:
        raise InputError(f"{video}: unsupported video format; use one of {', '.join(VIDEO_FORMATS)}")
    if renders is not None:
        if renders.exists() and not renders.is_dir():
            raise InputError(f"{renders}: exists and is not a folder")
        if not renders.exists():
            check_writable(renders)
    if len({p.resolve() for p in (output, cameras, video, report) if p is not None}) < sum(
        p is not None for p in (output, cameras, video, report)
    ):
        raise InputError("two outputs point at the same file")


def _reconstruct(
    *, images: list[Path], output: Path, cameras: Path | None, renders: Path | None, num_renders: int,
    video: Path | None, report: Path | None, json_out: bool, size: int, intrinsics: Path | None,
    focal: float | None, conf_threshold: float | None, refine_steps: int, refine_scale: int, use_mac: bool,
    quiet: bool, neural: dict[str, Any] | None = None, lpips_weights: Path | None = None,
) -> None:  # fmt: skip
    from ..errors import InputError
    from ..pipeline.run import Pipeline, ReconstructConfig
    from ..pipeline.views import ViewConfig

    cameras = cameras or output.with_name(output.stem + ".cameras.json")
    _check_outputs(output, cameras, renders, video, report)
    lpips = None
    if lpips_weights is not None:
        if refine_steps == 0:
            raise InputError("--lpips-weights is used by the refinement: add --refine STEPS or --refine auto")
        from ..lpips import load_lpips

        lpips = load_lpips(lpips_weights)
    config = ReconstructConfig(views=ViewConfig(size=size, intrinsics=intrinsics, focal=focal))

    with _StageProgress(disabled=quiet) as progress:
        if neural is not None:
            from ..pipeline.neural import (
                NeuralBackend,
                NeuralConfig,
                NeuralPipeline,
                load_neural_models,
                neural_reconstruct_config,
            )

            config = neural_reconstruct_config(config)
            if conf_threshold is not None:
                config.matching.conf_threshold = conf_threshold
            progress.event("weights", "start")
            t0 = time.perf_counter()
            try:
                models = load_neural_models(**{k: v for k, v in neural.items() if k != "precision"})
            except BaseException:
                progress.event("weights", "fail")
                raise
            load_s = time.perf_counter() - t0
            progress.event("weights", "end")
            backend = NeuralBackend(models, NeuralConfig(precision=neural["precision"]))
            pipeline: Pipeline = NeuralPipeline(backend, config)
        else:
            if conf_threshold is not None:
                config.matching.conf_threshold = conf_threshold
            pipeline = Pipeline(config)
        result = pipeline.run(images, on_stage=progress.event)
        if neural is not None:
            result.report["neural"]["load_s"] = load_s
        if refine_steps > 0:
            result = _refine(result, refine_steps, refine_scale, use_mac, progress, lpips)
        written = _write_outputs(result, output, cameras, renders, num_renders, video, progress)

    result.report["outputs"] = {k: str(v) for k, v in written.items()}
    if report is not None:
        from .._atomic import atomic_write_text

        atomic_write_text(report, json.dumps(result.report, indent=2) + "\n")
    if json_out:
        out_console.print_json(json.dumps(result.report))
    if not quiet:
        _summary(result.report, written)


def _refine(result, steps: int, scale: int, use_mac: bool, progress: _StageProgress, lpips=None):  # noqa: ANN001, ANN202
    import dataclasses

    from ..errors import InputError
    from ..refine import RefineConfig, refine

    h, w = result.maps[0].size
    if any(m.size[0] % scale or m.size[1] % scale for m in result.maps):
        raise InputError(f"--refine-scale {scale}: the working size {w}x{h} is not divisible by it")
    cfg = RefineConfig(steps=steps, scale=scale, use_mac=use_mac)
    progress.event("refine", "start")
    task = progress.progress.add_task("", total=steps, took="")

    def on_step(step: int, terms: dict[str, float]) -> None:
        mac = f", mac {terms['mac']:.4f}" if "mac" in terms else ""
        mac += f", lpips {terms['lpips']:.4f}" if "lpips" in terms else ""
        progress.progress.update(task, completed=step, took=f"step {step}/{steps}: photo {terms['photo']:.4f}{mac}")

    out = refine(result.views, result.geometry, result.maps, cfg, depths=result.depths, lpips=lpips, on_step=on_step)
    progress.progress.remove_task(task)
    progress.event("refine", "end")
    report = dict(result.report)
    report["refine"] = {
        "steps": out.steps,
        "max_steps": steps,
        "stopped_early": out.stopped_early,
        "seconds": out.seconds,
        "scale": scale,
        "mac": use_mac,
        "lpips": lpips is not None,
        "loss_first": out.history[0],
        "loss_last": out.history[-1],
    }
    times = {k: v for k, v in report["times_s"].items() if k != "total"}
    report["times_s"] = {**times, "refine": out.seconds, "total": report["times_s"]["total"] + out.seconds}
    report["gaussians"] = int(sum(int(m.valid.sum()) for m in out.maps))
    return dataclasses.replace(result, maps=out.maps, report=report)


def _write_outputs(result, output, cameras, renders, num_renders, video, progress) -> dict[str, Any]:  # noqa: ANN001
    import torch

    from ..cameras import save_cameras
    from ..images import save_image, to_uint8, write_video
    from ..ply import write_ply
    from ..render import render_camera
    from ..trajectory import interpolate_cameras

    written: dict[str, Any] = {}
    progress.event("write", "start")
    n = write_ply(output, result.gaussians)
    result.report["gaussians_written"] = n
    written["scene"] = output
    save_cameras(cameras, result.cameras())
    written["cameras"] = cameras
    progress.event("write", "end")
    if renders is not None or video is not None:
        progress.event("renders", "start")
        work_cams = result.cameras(original_size=False)
        path = interpolate_cameras(list(work_cams), num_renders)
        frames = []
        with torch.no_grad():
            for cam in path:
                frames.append(to_uint8(render_camera(result.gaussians, cam).rgb))
        if renders is not None:
            renders.mkdir(parents=True, exist_ok=True)
            for i, f in enumerate(frames):
                save_image(renders / f"view_{i:03d}.png", f)
            written["renders"] = renders
        if video is not None:
            write_video(video, frames)
            written["video"] = video
        progress.event("renders", "end")
    return written


class _StageProgress:
    """One line per stage: a spinner while it runs, then a tick and its wall time."""

    def __init__(self, disabled: bool) -> None:
        from rich.progress import Progress, SpinnerColumn, TextColumn

        self.progress = Progress(
            SpinnerColumn(finished_text="[green]✓[/]"), TextColumn("{task.description:<22}"),
            TextColumn("{task.fields[took]}"), console=err_console, disable=disabled, transient=False,
        )  # fmt: skip
        self.tasks: dict[str, Any] = {}
        self.started: dict[str, float] = {}

    def __enter__(self) -> _StageProgress:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        for stage, task in self.tasks.items():  # a stage interrupted by an error stops its spinner
            if stage in self.started:
                self.progress.update(task, took="[red]✗ failed[/]")
            self.progress.stop_task(task)
        self.progress.stop()

    def event(self, stage: str, kind: str) -> None:
        import time

        if kind == "start":
            self.started[stage] = time.perf_counter()
            self.tasks[stage] = self.progress.add_task(stage, total=1, took="")
        elif kind == "fail":
            self.started.pop(stage, None)
            self.progress.update(self.tasks[stage], took="[red]✗ failed[/]")
            self.progress.stop_task(self.tasks[stage])
        else:
            took = time.perf_counter() - self.started.pop(stage)
            self.progress.update(self.tasks[stage], completed=1, took=f"{took:.2f} s")
            self.progress.stop_task(self.tasks[stage])


def _summary(report: dict[str, Any], written: dict[str, Any]) -> None:
    from rich.table import Table

    t = Table(title="macsplat reconstruct", show_header=False, title_justify="left")
    t.add_column(style="bold")
    t.add_column()
    imgs = report["images"]
    t.add_row(
        "images",
        "\n".join(
            f"{Path(p).name}: {i['original_size'][0]}x{i['original_size'][1]} → {i['working_size'][0]}x"
            f"{i['working_size'][1]}, focal {i['focal_px_working']:.0f} px ({i['intrinsics_source']})"
            for p, i in zip(report["inputs"], imgs)
        ),
    )
    m = report["matches"]
    t.add_row("keypoints", " / ".join(str(k) for k in report["keypoints"]))
    t.add_row("matches", " → ".join(f"{v} {k}" for k, v in m.items()))
    pose = report["pose"]

    def num(key: str, fmt: str) -> str:
        v = pose.get(key)
        return format(v, fmt) if isinstance(v, (int, float)) else "n/a"

    line = (
        f"rotation {num('rotation_deg', '.1f')}°, median parallax {num('median_parallax_deg', '.1f')}°, "
        f"inlier ratio {num('inlier_ratio', '.2f')}, median epipolar error {num('median_sampson_px', '.2f')} px"
    )
    if "translation_norm" in pose:
        line += f", baseline {num('translation_norm', '.3f')} m"
    t.add_row("pose", line)
    if "neural" in report:
        n = report["neural"]
        t.add_row("backend", f"neural ({n['device']}): forward pass {n['forward_s']:.2f} s")
        t.add_row("fusion", n["fusion"]["detail"])
    t.add_row("depth", " / ".join(f"{100 * c:.0f} %" for c in report["depth_coverage"]) + " of pixels")
    t.add_row("Gaussians", f"{report.get('gaussians_written', report['gaussians']):,}")
    times = report["times_s"]
    t.add_row("time", ", ".join(f"{k} {v:.2f} s" for k, v in times.items()))
    t.add_row("wrote", "\n".join(str(v) for v in written.values()))
    err_console.print(t)
