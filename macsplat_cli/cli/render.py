"""``macsplat render``: render a 3DGS PLY from a camera, or along a path between cameras."""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from .._limits import MAX_PATH_VIEWS
from ._app import app
from ._common import QuietOpt, VerboseOpt, check_no_clobber, command_context, err_console, escape
from ._options import choice

if TYPE_CHECKING:
    from ..render.rasterize import Backend as Rasterizer

logger = logging.getLogger("macsplat_cli.cli.render")

_NAMED_COLOURS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5)}


RASTERIZERS: tuple[Rasterizer, ...] = ("auto", "numba", "torch", "gsplat")
"""``--backend``: :data:`macsplat_cli.render.rasterize.Backend`'s names, here so that ``--help`` loads no torch."""


def parse_colour(text: str) -> tuple[float, float, float]:
    """``black``/``white``/``gray``, ``#rrggbb``, or ``r,g,b`` with values in [0, 1]."""
    from ..errors import InputError

    t = text.strip().lower()
    if t in _NAMED_COLOURS:
        return _NAMED_COLOURS[t]
    if re.fullmatch(r"#[0-9a-f]{6}", t):
        r, g, b = (int(t[i : i + 2], 16) / 255.0 for i in (1, 3, 5))
        return r, g, b
    parts = t.split(",")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(0.0 <= v <= 1.0 for v in vals):
        raise InputError(f"--background {text!r}: use black, white, gray, #rrggbb or r,g,b with values in [0, 1]")
    return vals[0], vals[1], vals[2]


@app.command("render")
def render_command(
    ctx: typer.Context,
    scene: Annotated[Path, typer.Argument(metavar="SCENE.ply", help="A 3DGS scene in the standard PLY layout.")],
    output: Annotated[
        Path | None,
        typer.Option(
            "--output", "-o", help="Image to write (.png/.jpg/.webp/.tif/.bmp); with --path, a folder of frames."
        ),
    ] = None,
    pose: Annotated[
        Path | None, typer.Option("--pose", metavar="CAM.json", help="Camera file (macsplat cameras schema).")
    ] = None,
    cameras: Annotated[
        Path | None, typer.Option("--cameras", metavar="CAMS.json", help="Camera file; same as --pose.")
    ] = None,
    view: Annotated[int, typer.Option("--view", min=0, help="Which camera of the file to render.")] = 0,
    path: Annotated[
        int | None,
        typer.Option(
            "--path",
            min=1,
            max=MAX_PATH_VIEWS,
            metavar="N",
            help=f"Render N views (at most {MAX_PATH_VIEWS:,}) along the path through all cameras of the file.",
        ),
    ] = None,
    width: Annotated[int | None, typer.Option("--width", min=1, help="Output width (K is rescaled).")] = None,
    height: Annotated[int | None, typer.Option("--height", min=1, help="Output height (K is rescaled).")] = None,
    background: Annotated[
        str, typer.Option("--background", help="black, white, gray, #rrggbb or r,g,b in [0, 1].")
    ] = "black",
    depth: Annotated[
        Path | None,
        typer.Option("--depth", help="Also write the expected depth: .npy/.tif (float32) or .png (16-bit, x1000)."),
    ] = None,
    video: Annotated[
        Path | None, typer.Option("--video", help="With --path: also write the frames as .mp4 or .gif.")
    ] = None,
    fps: Annotated[float, typer.Option("--fps", help="Video frame rate (0.01 to 240).")] = 24.0,
    backend: Annotated[str, typer.Option("--backend", metavar="|".join(RASTERIZERS), help="Rasterizer.")] = "auto",
    device: Annotated[str, typer.Option("--device", metavar="cpu|cuda", help="Where to render.")] = "cpu",
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Render a Gaussian scene from a camera, or a path of views between cameras.

    [bold]Examples[/]

      macsplat render scene.ply --pose cam.json -o view.png --depth depth.npy
      macsplat render scene.ply --cameras cams.json --path 60 -o frames/ --video orbit.mp4
    """
    with command_context(ctx, verbose, quiet) as state:
        _render(
            scene=scene,
            output=output,
            camera_file=_one_camera_file(pose, cameras),
            view=view,
            path=path,
            width=width,
            height=height,
            background=parse_colour(background),
            depth=depth,
            video=video,
            fps=fps,
            backend=choice("--backend", backend, RASTERIZERS, sep=", "),
            device=choice("--device", device, ("cpu", "cuda")),
            quiet=state.quiet,
        )


def _one_camera_file(pose: Path | None, cameras: Path | None) -> Path:
    from ..errors import InputError

    if pose is None:
        if cameras is None:
            raise InputError("a camera file is required: --pose CAM.json (or --cameras CAMS.json)")
        return cameras
    if cameras is not None and pose != cameras:
        raise InputError("give one camera file: --pose and --cameras are the same option")
    return pose


def _render(
    *,
    scene: Path,
    output: Path | None,
    camera_file: Path,
    view: int,
    path: int | None,
    width: int | None,
    height: int | None,
    background: tuple[float, float, float],
    depth: Path | None,
    video: Path | None,
    fps: float,
    backend: str,
    device: str,
    quiet: bool,
) -> None:
    from ..ply import read_ply

    # ---- validate everything before any work, so bad input fails fast and writes nothing
    frame_files = _check_outputs(scene, camera_file, output, path, depth, video, fps)
    _check_device(backend, device)

    t0 = time.perf_counter()
    targets, n_cams = _targets(camera_file, view, path, width, height, video)
    gaussians = read_ply(scene).to(device)
    t_load = time.perf_counter() - t0
    logger.debug("loaded %d Gaussians (SH degree %d) and %d camera(s)", len(gaussians), gaussians.sh_degree, n_cams)
    t0 = time.perf_counter()
    written, n_visible = _render_targets(
        gaussians, targets, output, frame_files, depth, video, fps, background, backend, single=path is None,
        quiet=quiet,
    )  # fmt: skip
    t_render = time.perf_counter() - t0

    if not quiet:
        _summary(scene, len(gaussians), targets, n_visible, t_load, t_render, written, backend)


def _check_outputs(
    scene: Path, camera_file: Path, output: Path | None, path: int | None, depth: Path | None, video: Path | None,
    fps: float,
) -> list[Path]:  # fmt: skip
    """Every file the command will write checked (formats, clobbering, writability, the video's frame rate); returns
    the ``--path`` frames."""
    from .._atomic import check_writable
    from ..errors import InputError
    from ..images import DEPTH_FORMATS, VIDEO_FORMATS, check_fps, check_image_path

    writes: list[Path] = []  # every file written, checked by check_writable after the clobber check
    if path is None:
        if output is None:
            raise InputError("--output/-o is required: the image to write")
        if video is not None:
            raise InputError("--video needs --path N (a path of views to put in the video)")
        check_image_path(output)
        writes.append(output)
        if depth is not None:
            if depth.suffix.lower() not in DEPTH_FORMATS:
                raise InputError(f"{depth}: unsupported depth format; use one of {', '.join(DEPTH_FORMATS)}")
            writes.append(depth)
    else:
        if output is None and video is None:
            raise InputError("with --path, give a frame folder (-o DIR) and/or a video (--video FILE)")
        if depth is not None:
            raise InputError("--depth writes a single view; it cannot be combined with --path")
        if output is not None:
            if output.exists() and not output.is_dir():
                raise InputError(f"{output}: exists and is not a folder (with --path, -o names a folder of frames)")
        if video is not None:
            if video.suffix.lower() not in VIDEO_FORMATS:
                raise InputError(f"{video}: unsupported video format; use one of {', '.join(VIDEO_FORMATS)}")
            check_fps(fps)  # OpenCV's writer never returns for an infinite rate
            writes.append(video)
    frame_files = [] if path is None or output is None else [output / f"frame_{i:04d}.png" for i in range(path)]
    single = [("-o", output), ("--depth", depth)] if path is None else [("--video", video)]
    check_no_clobber([*single, *(("-o", f) for f in frame_files)], [("SCENE.ply", scene), ("--pose", camera_file)])
    for f in [*writes, *frame_files]:  # links, devices, unwritable folders (an existing frame folder too)
        check_writable(f)
    return frame_files


def _check_device(backend: str, device: str) -> None:
    import torch

    from ..errors import InputError

    if device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: this PyTorch has no CUDA device")
    if backend == "gsplat" and device != "cuda":
        raise InputError("--backend gsplat renders on a CUDA device: add --device cuda")


def _targets(
    camera_file: Path, view: int, path: int | None, width: int | None, height: int | None, video: Path | None
) -> tuple[list, int]:  # fmt: skip
    """The cameras to render (one view of the file, or ``path`` views along it, checked by
    :func:`~macsplat_cli._limits.check_path_views`) and the number in the file."""
    from .._limits import check_path_views
    from ..cameras import load_cameras
    from ..errors import InputError
    from ..trajectory import interpolate_cameras

    cams = load_cameras(camera_file)
    if path is None:
        if view >= len(cams):
            raise InputError(f"{camera_file}: --view {view} is out of range (the file has {len(cams)} camera(s))")
        return [_resized(cams[view], width, height)], len(cams)
    w = width or (round(height * cams[0].width / cams[0].height) if height else None)
    h = height or (round(width * cams[0].height / cams[0].width) if width else None)
    check_path_views("--path", path, w or cams[0].width, h or cams[0].height, video)
    return interpolate_cameras(list(cams), path, width=w, height=h), len(cams)


def _render_targets(
    gaussians, targets: list, output: Path | None, frame_files: list[Path], depth: Path | None,  # noqa: ANN001
    video: Path | None, fps: float, background: tuple[float, float, float], backend: str, *, single: bool,
    quiet: bool,
) -> tuple[list[Path], list[int]]:  # fmt: skip
    """Render every target and write it as it is rendered (each file atomically; the video's frames into its
    temporary file, :func:`~macsplat_cli.images.video_writer`). Returns the files written and the Gaussians visible
    in each view."""
    import contextlib

    import torch

    from ..errors import OutputPathError
    from ..images import save_depth, save_image, to_uint8, video_writer
    from ..render import render_camera

    written, n_visible = [], []
    if not single and output is not None:
        try:
            output.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputPathError(f"cannot create folder {output}: {e.strerror or e}") from None
    with contextlib.ExitStack() as stack:
        add_frame = stack.enter_context(video_writer(video, fps)) if video is not None else None
        stack.enter_context(torch.no_grad())
        advance = stack.enter_context(_progress(len(targets), quiet or len(targets) == 1))
        for k, cam in enumerate(targets):
            out = render_camera(gaussians, cam, background=background, backend=backend)
            n_visible.append(int(out.visible.numel()))
            if single:
                assert output is not None  # a single view is written to -o (checked with the outputs)
                written.append(save_image(output, out.rgb))
                if depth is not None:
                    written.append(save_depth(depth, out.depth))
            else:
                img = to_uint8(out.rgb)
                if output is not None:
                    written.append(save_image(frame_files[k], img))
                if add_frame is not None:
                    add_frame(img)
            advance()
    if video is not None:
        written.append(video)
    return written, n_visible


def _resized(cam, width: int | None, height: int | None):  # noqa: ANN001, ANN202
    if width is None and height is None:
        return cam
    w = width or round(height * cam.width / cam.height)
    h = height or round(width * cam.height / cam.width)
    return cam.rescaled(w, h)


class _progress:
    """A Rich progress bar on stderr (nothing when disabled); yields an ``advance()`` callable."""

    def __init__(self, total: int, disabled: bool) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.progress = Progress(
            TextColumn("rendering"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            console=err_console,
            disable=disabled,
            transient=True,
        )
        self.total = total

    def __enter__(self):  # noqa: ANN204
        self.progress.start()
        task = self.progress.add_task("render", total=self.total)
        return lambda: self.progress.advance(task)

    def __exit__(self, *exc: object) -> None:
        self.progress.stop()


def _summary(scene, n_gauss, targets, n_visible, t_load, t_render, written, backend) -> None:  # noqa: ANN001
    from rich.table import Table

    table = Table(title="macsplat render", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    table.add_row("scene", f"{escape(str(scene))} ({n_gauss:,} Gaussians)")
    table.add_row("views", f"{len(targets)} at {targets[0].width}x{targets[0].height}")
    table.add_row("visible", f"{min(n_visible):,}–{max(n_visible):,}" if len(n_visible) > 1 else f"{n_visible[0]:,}")
    table.add_row("backend", escape(backend))
    per_view = f"{1e3 * t_render / len(targets):.0f} ms/view"
    table.add_row("time", f"load {t_load:.2f} s, render + write {t_render:.2f} s ({per_view})")
    shown = written if len(written) <= 4 else [*written[:2], f"... ({len(written) - 3} more)", written[-1]]
    table.add_row("wrote", "\n".join(escape(str(p)) for p in shown))
    err_console.print(table)
