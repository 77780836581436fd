"""``macsplat reconstruct``: two photos → a 3DGS PLY, the cameras, novel views, a report."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from .._limits import MAX_PATH_VIEWS
from ..presets import BACKENDS, DEFAULT_MATCHER, QUALITIES
from ._app import app
from ._common import (
    QuietOpt,
    StageProgress,
    VerboseOpt,
    check_no_clobber,
    command_context,
    err_console,
    expand_photos,
    out_console,
)
from ._export import OutputExtras, export_requests, up_choice
from ._options import (
    AcceptLowConfidenceOpt,
    DeviceOpt,
    DinoOpt,
    FusionOpt,
    GaussianHeadOpt,
    MatcherOpt,
    PrecisionOpt,
    RefineOpt,
    WeightsOpt,
    choice,
    neural_options,
    parse_refine,
)

if TYPE_CHECKING:
    from ..engine import EngineConfig
    from ..pipeline.run import Reconstruction

logger = logging.getLogger("macsplat_cli.cli.reconstruct")


CamerasOpt = Annotated[
    Path | None, typer.Option("--cameras", help="Where to write the estimated cameras [default: <stem>.cameras.json].")
]
RendersOpt = Annotated[
    Path | None, typer.Option("--renders", help="Folder for novel views along the path between the cameras.")
]
NumRendersOpt = Annotated[
    int,
    typer.Option(
        "--num-renders", min=2, max=MAX_PATH_VIEWS, help=f"Number of novel views (at most {MAX_PATH_VIEWS:,})."
    ),
]
VideoOpt = Annotated[Path | None, typer.Option("--video", help="Also write the novel views as .mp4 or .gif.")]
ReportOpt = Annotated[Path | None, typer.Option("--report", help="Write the run report (JSON) here.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the report as JSON on stdout.")]
SizeOpt = Annotated[
    int | None,
    typer.Option(
        "--size", min=64, help="Long side of the working images (multiple of 16) [default: 384 fast, else 512]."
    ),
]
QualityOpt = Annotated[
    str,
    typer.Option(
        "--quality",
        metavar="|".join(QUALITIES),
        help="How much the scene is compacted (merged, pruned) and how light the stages are; best: lossless.",
    ),
]
BudgetOpt = Annotated[
    int | None, typer.Option("--budget", min=1, metavar="N", help="At most N Gaussians in the scene.")
]
IntrinsicsOpt = Annotated[
    Path | None, typer.Option("--intrinsics", help="Camera file (cameras schema) with the photos' intrinsics.")
]
PosesOpt = Annotated[
    Path | None,
    typer.Option(
        "--poses",
        help="Camera file (cameras schema) with every photo's pose: no pose is estimated, the scene comes out in its "
        "frame and scale (metric when the file says so); its intrinsics are used unless --intrinsics is given.",
    ),
]
FocalOpt = Annotated[float | None, typer.Option("--focal", help="Focal length in pixels of the original photos.")]
ConfThresholdOpt = Annotated[
    float | None,
    typer.Option(
        "--conf-threshold",
        help="τ: keep matches whose joint confidence c0·c1 exceeds it [default: 0.04; 1 with --backend neural].",
    ),
]
FarLayerOpt = Annotated[
    bool,
    typer.Option(
        "--far-layer/--no-far-layer",
        help="Surround the scene with a far background layer extended from the photos' borders, so views past "
        "both photos show no empty band; --no-far-layer leaves those pixels to the renderer's --background.",
    ),
]
RefineScaleOpt = Annotated[
    int | None,
    typer.Option(
        "--refine-scale",
        min=1,
        max=4,
        show_default=False,
        help="Refine at 1/N resolution (default 2: ~4x faster per step than 1; 1 for --quality best on three photos "
        "or more).",
    ),
]
NoMacOpt = Annotated[bool, typer.Option("--no-mac", help="Refine without the MAC loss (ablation).")]
LpipsWeightsOpt = Annotated[
    Path | None,
    typer.Option(
        "--lpips-weights",
        metavar="PATH",
        help="Add LPIPS to the refinement's loss: a folder with torchvision's vgg16-*.pth and LPIPS v0.1 vgg.pth.",
    ),
]
ExportOpt = Annotated[
    tuple[str, Path] | None,
    typer.Option(
        "--export",
        metavar="FORMAT DIR",
        help="Also write the cameras, the verified points and the photos for other tools: 'colmap DIR' (a COLMAP "
        "text model in DIR/sparse/0, photos in DIR/images) or 'nerfstudio DIR' (transforms.json, sparse_pc.ply, "
        "images/).",
    ),
]
ForceOpt = Annotated[
    bool, typer.Option("--force", help="With --export: replace an export folder that exists and is not empty.")
]
UpOpt = Annotated[
    str,
    typer.Option(
        "--up",
        metavar="camera|auto",
        help="The world's up: camera = the first camera's frame as it is (y down); auto = rotated so that the "
        "cameras' mean up is +y (viewers that orbit about +y), for the scene and every camera written.",
    ),
]
BackendOpt = Annotated[
    str,
    typer.Option(
        "--backend",
        metavar="|".join(BACKENDS),
        help="classical: no learned weights (default); neural: MASt3R point maps and descriptors (--weights).",
    ),
]


@app.command("reconstruct")
def reconstruct_command(
    ctx: typer.Context,
    images: Annotated[
        list[Path],
        typer.Argument(
            metavar="PHOTOS...",
            help="Two or more photos of the scene (the first registered one defines the world frame), or a folder "
            "of photos.",
        ),
    ],
    output: Annotated[Path, typer.Option("--output", "-o", help="The Gaussian scene to write (.ply).")],
    cameras: CamerasOpt = None,
    renders: RendersOpt = None,
    num_renders: NumRendersOpt = 10,
    video: VideoOpt = None,
    report: ReportOpt = None,
    json_out: JsonOpt = False,
    size: SizeOpt = None,
    quality: QualityOpt = "balanced",
    budget: BudgetOpt = None,
    intrinsics: IntrinsicsOpt = None,
    poses: PosesOpt = None,
    focal: FocalOpt = None,
    conf_threshold: ConfThresholdOpt = None,
    accept_low_confidence: AcceptLowConfidenceOpt = False,
    far_layer: FarLayerOpt = True,
    refine: RefineOpt = None,
    refine_scale: RefineScaleOpt = None,
    no_mac: NoMacOpt = False,
    lpips_weights: LpipsWeightsOpt = None,
    backend: BackendOpt = "classical",
    matcher: MatcherOpt = DEFAULT_MATCHER,
    weights: WeightsOpt = None,
    dino: DinoOpt = None,
    fusion: FusionOpt = None,
    gaussian_head: GaussianHeadOpt = None,
    device: DeviceOpt = "cpu",
    precision: PrecisionOpt = "fp32",
    export: ExportOpt = None,
    force: ForceOpt = False,
    up: UpOpt = "camera",
    view: Annotated[
        bool, typer.Option("--view", help="Then show the scene in the browser (macsplat view; needs macsplat[view]).")
    ] = False,
    view_port: Annotated[
        int, typer.Option("--view-port", min=0, max=65535, help="With --view: the port on 127.0.0.1 (0: a free one).")
    ] = 8080,
    profile: Annotated[
        bool, typer.Option("--profile", help="Then print each stage's seconds and memory (a table on stderr).")
    ] = False,
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Reconstruct a Gaussian splat scene from two or more photos.

    Writes the scene (standard 3DGS PLY), the estimated cameras (world = first camera;
    relative scale, baseline 1, with the classical backend; metres with the neural one), and
    optionally novel views, a video and a JSON report. More than two photos (up to 64; tested
    to 32) are registered in one frame; a photo that cannot be is left out with its reason.
    The default backend needs no learned weights; [bold]--backend neural[/] uses MASt3R
    (user-supplied checkpoint, see models/), two photos only.

    [bold]Examples[/]

      macsplat reconstruct a.jpg b.jpg -o scene.ply --renders views/ --video path.mp4

      macsplat reconstruct photos/*.jpg -o scene.ply

      macsplat reconstruct a.jpg b.jpg -o scene.ply --backend neural --weights mast3r.pth
    """
    started = time.perf_counter()
    with command_context(ctx, verbose, quiet) as state:
        if view:  # the viewer's extra and its port are checked before the work, not after it
            from .view import check_viewer

            check_viewer("127.0.0.1", view_port)
        config = reconstruct_config(
            size=size, quality=quality, budget=budget, intrinsics=intrinsics, poses=poses, focal=focal,
            conf_threshold=conf_threshold, accept_low_confidence=accept_low_confidence, far_layer=far_layer,
            refine=refine, refine_scale=refine_scale, no_mac=no_mac, lpips_weights=lpips_weights, backend=backend,
            weights=weights, dino=dino, fusion=fusion, gaussian_head=gaussian_head, device=device, precision=precision,
            matcher=matcher,
        )  # fmt: skip
        _reconstruct(
            expand_photos(images), config, output=output, cameras=cameras, renders=renders, num_renders=num_renders,
            video=video, report=report, json_out=json_out, quiet=state.quiet, profile_from=started if profile else None,
            extras=OutputExtras(exports=export_requests([export] if export else []), force=force, up=up_choice(up)),
        )  # fmt: skip
        if view:
            from .view import view_files

            photos = expand_photos(images)
            folders = list(dict.fromkeys(p.parent for p in photos))
            cameras = cameras or output.with_name(output.stem + ".cameras.json")
            view_files(output, cameras, folders, port=view_port, quiet=state.quiet)


def reconstruct_config(
    *, size: int | None = None, quality: str = "balanced", budget: int | None = None, intrinsics: Path | None = None,
    poses: Path | None = None, focal: float | None = None, conf_threshold: float | None = None,
    accept_low_confidence: bool = False,
    far_layer: bool = True, refine: str | None = None, refine_scale: int | None = None, no_mac: bool = False,
    lpips_weights: Path | None = None, backend: str = "classical", weights: Path | None = None,
    dino: Path | None = None, fusion: Path | None = None, gaussian_head: Path | None = None, device: str = "cpu",
    precision: str = "fp32", matcher: str = DEFAULT_MATCHER,
) -> EngineConfig:  # fmt: skip
    """``reconstruct``'s options (the command's defaults) as the engine takes them, one field each: the presets
    apply in the engine (:meth:`~macsplat_cli.engine.EngineConfig.settings`), the choices are checked here
    (:func:`~._options.choice`), their combinations by :meth:`~macsplat_cli.engine.EngineConfig.validate`.

    Raises:
        InputError: an unknown choice; ``--refine`` is not ``STEPS|auto|off`` (:func:`~._options.parse_refine`).
    """
    from ..engine import EngineConfig
    from ..pipeline.background import BackgroundConfig
    from ..pipeline.multiview import MultiViewConfig
    from ..pipeline.pose import PoseSearchConfig
    from ..pipeline.refine_config import RefineConfig
    from ..pipeline.run import ReconstructConfig
    from ..pipeline.views import ViewConfig
    from ..presets import BACKENDS, MATCHERS, QUALITIES, Overrides

    return EngineConfig(  # their combinations are checked by EngineConfig.validate
        quality=choice("--quality", quality, QUALITIES, sep=", "),  # in check_choices' order
        backend=choice("--backend", backend, BACKENDS),
        matcher=choice("--matcher", matcher, MATCHERS, sep=", "),
        overrides=Overrides(
            size=size,
            conf_threshold=conf_threshold,
            budget=budget,
            refine=parse_refine(refine),
            refine_scale=refine_scale,
        ),
        pipeline=ReconstructConfig(
            views=ViewConfig(
                intrinsics=intrinsics if intrinsics is not None or focal is not None else poses, focal=focal
            ),  # fmt: skip
            search=PoseSearchConfig(accept_low_confidence=accept_low_confidence),
            background=BackgroundConfig(enabled=far_layer),
            multiview=MultiViewConfig(poses=poses),
        ),
        neural=neural_options(weights, gaussian_head, dino, fusion, device, precision),
        refine=RefineConfig(use_mac=not no_mac, lpips_weights=lpips_weights),
    )


def _check_outputs(
    output: Path,
    cameras: Path,
    renders: Path | None,
    num_renders: int,
    video: Path | None,
    report: Path | None,
    inputs: Sequence[tuple[str, Path | None]] = (),
    long_side: int = 512,
) -> None:
    """Every output writable, none an input or another output, the novel views within
    :func:`~macsplat_cli._limits.check_path_views` (frames at most ``long_side`` a side): checked before the first
    stage."""
    from .._atomic import check_writable
    from .._limits import check_path_views
    from ..errors import InputError
    from ..images import VIDEO_FORMATS

    if output.suffix.lower() != ".ply":
        raise InputError(f"{output}: the scene is written as a .ply file")
    if renders is not None or video is not None:
        check_path_views("--num-renders", num_renders, long_side, long_side, video)
    views = _render_names(renders, num_renders)
    outputs = [("-o", output), ("--cameras", cameras), ("--video", video), ("--report", report)]
    # first: an output that is an input (also through a link) is named as such, not as "a link"
    check_no_clobber([*outputs, *(("--renders", p) for p in views)], inputs)
    for p in (output, cameras, video, report):
        if p is not None:
            check_writable(p)
    if video is not None and video.suffix.lower() not in VIDEO_FORMATS:
        raise InputError(f"{video}: unsupported video format; use one of {', '.join(VIDEO_FORMATS)}")
    if renders is not None:
        if renders.exists() and not renders.is_dir():
            raise InputError(f"{renders}: exists and is not a folder")
        for p in views:  # an existing folder must be writable too, and hold no folder where a view goes
            check_writable(p)


def _frame_side(config: EngineConfig) -> int:
    """The novel views' longest possible side: the working size's long side, which the rounding of each side to a
    multiple of 16 (:func:`~macsplat_cli.pipeline.views.working_size`) may raise by less than 16."""
    return config.settings().pipeline.views.size + 16


def _render_names(renders: Path | None, num_renders: int) -> list[Path]:
    """The files written into --renders."""
    return [] if renders is None else [renders / f"view_{i:03d}.png" for i in range(num_renders)]


def _reconstruct(
    images: list[Path], config: EngineConfig, *, output: Path, cameras: Path | None, renders: Path | None,
    num_renders: int, video: Path | None, report: Path | None, json_out: bool, quiet: bool,
    profile_from: float | None = None, extras: OutputExtras | None = None,
) -> None:  # fmt: skip
    """Options → engine → files: the outputs are checked, the engine runs, then the files are written. With
    ``profile_from`` (the command's start, ``perf_counter``), a table of each stage's time and memory follows;
    ``extras``: the exports and the world's up (:mod:`._export`)."""
    from ..engine import reconstruct
    from ._export import check_exports

    cameras = cameras or output.with_name(output.stem + ".cameras.json")
    n = config.neural
    inputs = [*((f"photo {k + 1}", p) for k, p in enumerate(images)),
              ("--intrinsics", config.pipeline.views.intrinsics),
              ("--poses", config.pipeline.multiview.poses),
              ("--weights", n.weights), ("--gaussian-head", n.gaussian_head), ("--dino", n.dino),
              ("--fusion", n.fusion), ("--lpips-weights", config.refine.lpips_weights)]  # fmt: skip
    _check_outputs(output, cameras, renders, num_renders, video, report, inputs, _frame_side(config))
    extras = extras or OutputExtras()
    check_exports(extras, [*inputs, ("-o", output), ("--cameras", cameras), ("--video", video), ("--report", report),
                           ("--renders", renders)], images)  # fmt: skip
    from ._profile import StageProfile

    profile = StageProfile(started=profile_from) if profile_from is not None else None
    with StageProgress(disabled=quiet, also=profile.event if profile else None) as progress:
        result = reconstruct(images, config, on_stage=progress.event, on_refine_step=progress.refine_step)
        written, n_written = _write_outputs(result, output, cameras, renders, num_renders, video, progress, extras)

    result.report.add_outputs(written, gaussians_written=n_written)
    doc = result.report.to_json()
    if report is not None:
        from .._atomic import atomic_write_text

        atomic_write_text(report, json.dumps(doc, indent=2) + "\n")
    if json_out:
        out_console.print_json(json.dumps(doc))
    if not quiet:
        from ._summary import summary

        summary(result.report, written)
    if profile is not None:
        err_console.print(profile.table())


def _write_outputs(
    result: Reconstruction, output: Path, cameras: Path, renders: Path | None, num_renders: int, video: Path | None,
    progress: StageProgress, extras: OutputExtras,
) -> tuple[dict[str, Path], int]:  # fmt: skip
    """The files: the scene, the cameras (in the world ``extras.up`` asks for), the exports, and the novel views
    (:func:`~macsplat_cli.engine.path_views`) as images and a video, each view written as it is rendered. Returns
    role → path of each file written, and the Gaussians the PLY holds."""
    import contextlib

    from ..cameras import save_cameras
    from ..engine import path_views
    from ..images import save_image, video_writer
    from ..ply import write_ply
    from ._export import world_outputs, write_exports

    written: dict[str, Path] = {}
    progress.event("write", "start")
    scene, camera_set, rotation = world_outputs(result, extras.up)
    n_written = write_ply(output, scene)
    written["scene"] = output
    save_cameras(cameras, camera_set)
    written["cameras"] = cameras
    written.update(write_exports(result, extras, rotation))
    progress.event("write", "end")
    if renders is not None or video is not None:
        progress.event("renders", "start")
        names = _render_names(renders, num_renders)
        if renders is not None:
            renders.mkdir(parents=True, exist_ok=True)
        with contextlib.ExitStack() as stack:
            add_frame = stack.enter_context(video_writer(video)) if video is not None else None
            for k, frame in enumerate(path_views(result, num_renders)):
                if renders is not None:
                    save_image(names[k], frame)
                if add_frame is not None:
                    add_frame(frame)
        if renders is not None:
            written["renders"] = renders
        if video is not None:
            written["video"] = video
        progress.event("renders", "end")
    return written, n_written
