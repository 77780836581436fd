"""``macsplat view``: look at a scene in the browser (the optional extra ``macsplat[view]``)."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ._app import app
from ._common import QuietOpt, VerboseOpt, command_context, err_console, escape

if TYPE_CHECKING:
    from ..cameras import Camera
    from ..gaussians import Gaussians

logger = logging.getLogger("macsplat_cli.cli.view")

HostOpt = Annotated[
    str, typer.Option("--host", help="Address to serve on; anything but loopback lets other machines see the scene.")
]
PortOpt = Annotated[int, typer.Option("--port", min=0, max=65535, help="Port; 0 picks a free one.")]
OpenOpt = Annotated[bool, typer.Option("--open/--no-open", help="Open the page in the default browser.")]


@app.command("view")
def view_command(
    ctx: typer.Context,
    scene: Annotated[Path, typer.Argument(metavar="SCENE.ply", help="A 3DGS scene in the standard PLY layout.")],
    cameras: Annotated[
        Path | None,
        typer.Option(
            "--cameras", metavar="CAMS.json", help="Cameras to draw [default: <stem>.cameras.json beside it]."
        ),
    ] = None,
    images: Annotated[
        Path | None,
        typer.Option("--images", metavar="DIR", help="Folder of the photos, shown in their cameras' frusta."),
    ] = None,
    budget: Annotated[
        int | None, typer.Option("--budget", min=1, metavar="N", help="Show only the N Gaussians that cover most.")
    ] = None,
    host: HostOpt = "127.0.0.1",
    port: PortOpt = 8080,
    open_browser: OpenOpt = True,
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Serve an interactive view of a Gaussian scene, with its cameras, until Ctrl-C.

    [bold]Examples[/]

      macsplat view out/scene.ply
      macsplat view scene.ply --cameras scene.cameras.json --images photos/ --port 0 --no-open
    """
    with command_context(ctx, verbose, quiet) as state:
        if images is not None and not _is_folder(images):
            from ..errors import InputError

            raise InputError(f"--images {images}: not a folder")
        camera_file = cameras if cameras is not None else _default_cameras(scene)
        folders = [p for p in (images, camera_file.parent if camera_file else None, scene.parent) if p is not None]
        check_viewer(host, port)
        view_files(scene, camera_file, folders, budget=budget, host=host, port=port, open_browser=open_browser,
                   quiet=state.quiet)  # fmt: skip


def check_viewer(host: str, port: int) -> None:
    """The extra installed and the port free (InputError, exit 2), before any work."""
    from ..viewer import resolve_port, viser_module

    viser_module()
    if port:
        resolve_port(host, port)


def view_files(
    scene: Path,
    cameras: Path | None,
    image_folders: list[Path],
    *,
    budget: int | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    open_browser: bool = True,
    quiet: bool = False,
) -> None:
    """Read the scene and its cameras, then :func:`serve_scene` them."""
    from ..ply import read_ply

    gaussians = read_ply(scene)
    cams = _load_cameras(cameras)
    serve_scene(gaussians, cams, title=scene.name, image_folders=image_folders, budget=budget, host=host, port=port,
                open_browser=open_browser, quiet=quiet)  # fmt: skip


def serve_scene(
    gaussians: Gaussians,
    cameras: list[Camera],
    *,
    title: str,
    image_folders: list[Path],
    budget: int | None,
    host: str,
    port: int,
    open_browser: bool,
    quiet: bool = False,
) -> None:
    """Check the address, build the page, print its URL and serve until Ctrl-C (KeyboardInterrupt propagates;
    the server is stopped on the way out). Used by ``view`` and ``reconstruct --view``."""
    from ..viewer import ViewerConfig, ViewerServer, is_loopback, load_thumbnails, resolve_port, thin_out, viser_module

    viser_module()  # the missing extra is said before anything else
    port = resolve_port(host, port)
    if not is_loopback(host):
        err_console.print(
            f"[yellow]warning:[/] serving on {escape(host)}: anyone who can reach this machine on port {port} can see "
            "the scene, its cameras and photos", markup=True, highlight=False, soft_wrap=True,
        )  # fmt: skip
    total = len(gaussians)
    if budget is not None:
        gaussians = thin_out(gaussians, budget)
    thumbnails = load_thumbnails(cameras, image_folders, ViewerConfig().thumbnail_long_side)
    server = ViewerServer(gaussians, cameras, thumbnails=thumbnails, title=title,
                          config=ViewerConfig(host=host, port=port))  # fmt: skip
    try:
        shown = f"{len(gaussians):,} of {total:,}" if len(gaussians) < total else f"{total:,}"
        if not quiet:
            err_console.print(f"viewer: {shown} Gaussians, {len(cameras)} cameras, {len(thumbnails)} photos")
        # the URL on stdout, alone on its line: what a script waits for (with --port 0 it is the only way to learn it)
        print(server.url, flush=True)
        if not quiet:
            err_console.print("Ctrl-C stops the viewer", style="dim")
        if open_browser:
            _open(server.url)
        server.wait()
    finally:
        server.stop()


def _is_folder(path: Path) -> bool:
    """``path.is_dir()``, False where the system refuses the path itself (too long a name, say)."""
    try:
        return path.is_dir()
    except (OSError, ValueError):
        return False


def _default_cameras(scene: Path) -> Path | None:
    candidate = scene.with_name(scene.stem + ".cameras.json")
    try:
        return candidate if candidate.is_file() else None
    except (OSError, ValueError):  # a name the system refuses (a 250-byte scene name gives a 259-byte one)
        return None


def _load_cameras(path: Path | None) -> list[Camera]:
    from ..cameras import load_cameras

    return [] if path is None else list(load_cameras(path).cameras)


def _open(url: str) -> None:
    """Open ``url`` in a graphical browser; on a machine without a display, only say where the page is (Python's
    ``webbrowser`` would start a text browser in this terminal)."""
    import webbrowser

    graphical = sys.platform in ("darwin", "win32") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )
    if not graphical:
        err_console.print(f"no display: open {url} in a browser", style="dim")
        return
    try:
        webbrowser.open(url)
    except webbrowser.Error as e:  # pragma: no cover - depends on the desktop
        logger.warning("could not open a browser (%s): open %s", e, url)
