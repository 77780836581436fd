"""Time and peak memory of `macsplat reconstruct P1 ... PN` against N, with pycolmap's SfM as a peer.

    python -m benchmarks.multiview_scaling                       # N = 2, 4, 8, 16, 32 (a few minutes on 2 cores)
    python -m benchmarks.multiview_scaling --sizes 2,4,8         # fewer sizes
    python -m benchmarks.multiview_scaling --table               # reprint the last run's table, run nothing
    python -m benchmarks.multiview_scaling --real co3d --data ../shared/data   # real photos: N = 2, 4, 8, 16, 20
    python -m benchmarks.multiview_scaling --quality fast        # another preset (default: balanced)

The photos: one synthetic room (``make_scene("room", 0)``) seen from an orbit of ``--step`` degree steps (4°: every
photo overlaps its neighbours), 512 x 384, 60° horizontal field of view, rendered once into ``--cache`` (kept
between runs) with the intrinsics file (one camera for every photo). N photos are the first N of the orbit, so each
larger N adds photos at the end of the same arc.

Per N, the CLI runs in a fresh process under ``/usr/bin/time -v`` (its peak RSS; without it, a helper process that
runs the CLI and reports ``RUSAGE_CHILDREN``): ``macsplat reconstruct <N photos> -o out.ply --intrinsics intr.json
--report r.json --quality Q -q`` (``--quality``, default ``balanced``: the CLI's default). The table: wall time
(Python start and imports included: a constant that cancels in the per-photo figure), seconds per photo added beyond
the first pair ``(t_N - t_2) / (N - 2)`` (the issue's target: <= 1.5 s), the same two for the CLI's CPU seconds
(user + system: on a shared machine a steadier figure than the wall time; with two cores busy it is up to twice the
wall time), the report's stage times, peak RSS in GB of 10^9 bytes (target at N = 32: <= 4 GB) and, when pycolmap is
installed, its incremental SfM on the same photos with the true K held fixed (``benchmarks._colmap_peer``: SIFT at
512 px, exhaustive matching, mapping; no dense stage) — seconds and photos registered.

``--real co3d`` runs the same table on real photos instead (issue 40: the per-photo figure on real photos too):
CO3D apple's 20 frames from the shared data folder (``--data``; read as :mod:`benchmarks._dev` reads them), N of
them evenly spaced over the 20 (frame order: the cameras file's; N = 2 takes the first and the last, as
``benchmarks.multiview_dev`` spaces them), 1066 x 1896 photos (at the CLI's working size, as any photo), each
photo's true intrinsics given (a cameras file written into ``--cache``); the pycolmap peer gets the same K.

A warm-up run (N = 3, untimed) compiles the Numba kernels into the default cache first, so that N = 2 does not pay
for them. The results go to ``<cache>/results.json`` (``results_co3d.json``, ``results_fast.json``,
``results_co3d_fast.json``: ``--real``, ``--quality``); ``--table`` reprints them. The load average before each run
is printed and kept (the machine may be shared).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from benchmarks._common import print_header, row

DEFAULT_CACHE = Path(tempfile.gettempdir()) / "macsplat_multiview_scaling"
STAGES = ("pairs", "register", "depth", "gaussians", "compact")
"""The stage columns of the table (the report's ``times_s`` keys); 'other' is the rest of the report's total
(reading the photos, writing the outputs). N = 2 takes the two-view path: its 'pairs' column is the sum of
:data:`TWO_VIEW_PAIR`, and it has no 'register'."""
TWO_VIEW_PAIR = ("descriptors", "matching", "pose", "pose confidence")
TIME = Path("/usr/bin/time")
ORBIT = 32
"""The orbit is laid out for this many photos, centred on the scene's front (azimuth 0); N photos are its first N."""
GB = 1e9


REAL_SCENES = ("co3d",)
"""``--real`` scenes (:mod:`benchmarks._dev`'s names)."""
REAL_SIZES = [2, 4, 8, 16, 20]
"""``--real co3d``'s default N: up to every one of CO3D apple's 20 frames."""


@dataclass
class Photos:
    """The photos to draw from: in order, the intrinsics file, K of each photo at its own resolution, and how N are
    chosen (the first N of the orbit, or N evenly spaced)."""

    paths: list[Path]
    intrinsics: Path
    K: list[list[list[float]]]
    """[3, 3] per photo at the photo's own resolution, pixel centres at +0.5."""
    spread: bool = False
    """N photos are N evenly spaced over all of them (first and last included), not the first N."""

    def chosen(self, n: int) -> list[int]:
        """The indices of the ``n`` photos a run of size ``n`` takes."""
        if not self.spread:
            return list(range(n))
        import numpy as np

        return sorted({int(round(x)) for x in np.linspace(0, len(self.paths) - 1, n)})


@dataclass
class SizeResult:
    """One N: what the CLI did, how long it took and how much memory it held; the peer's figures."""

    n: int
    ok: bool
    wall_s: float
    peak_rss_bytes: int
    times_s: dict[str, float]
    registered: int
    load_before: float
    """1-minute load average just before the run."""
    error: str = ""
    cpu_s: float | None = None
    """User + system CPU seconds of the CLI process: less sensitive to a shared machine's load than the wall time."""
    colmap_s: float | None = None
    colmap_registered: int | None = None
    colmap_error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def render_photos(cache: Path, n: int, step_deg: float) -> Photos:
    """The first ``n`` photos of the orbit, rendered into ``cache`` unless already there (keyed by the step)."""
    import numpy as np

    from macsplat_cli.cameras import CameraSet, save_cameras
    from macsplat_cli.datasets.synthetic import make_scene, orbit_cameras, render
    from macsplat_cli.images import save_image

    folder = cache / f"room0_512x384_fov60_step{step_deg:g}"
    names = [f"view{k:02d}" for k in range(n)]
    paths = [folder / f"{name}.png" for name in names]
    intr = folder / "intrinsics.json"
    scene = make_scene("room", 0)
    azimuths = [step_deg * (k - (ORBIT - 1) / 2) for k in range(n)]  # ORBIT photos would be centred on the front
    cams = orbit_cameras(scene, azimuths, width=512, height=384, fov_deg=60, names=names)
    if not (intr.exists() and all(p.exists() for p in paths)):
        folder.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        for cam, p in zip(cams, paths, strict=True):
            if not p.exists():
                save_image(p, render(scene, cam, supersample=1).image)
        save_cameras(intr, CameraSet([cams[0]]))
        print(f"rendered {n} photos into {folder} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return Photos(paths, intr, [np.asarray(c.K, dtype=np.float64).tolist() for c in cams])


def real_photos(cache: Path, data: Path, scene: str) -> Photos:
    """A real scene's frames (:func:`benchmarks._dev.dev_frames`) with their true intrinsics written into ``cache`` as
    a cameras file (one camera per photo, named after its file); N of them evenly spaced."""
    import numpy as np

    from benchmarks._dev import dev_frames, photo_size
    from macsplat_cli.cameras import Camera, CameraSet, save_cameras

    frames = dev_frames(data, scene)
    cache.mkdir(parents=True, exist_ok=True)
    intr = cache / f"{scene}_intrinsics.json"
    save_cameras(intr, CameraSet([Camera(f.image.name, *photo_size(f), f.camera.K, np.eye(4)) for f in frames]))
    Ks = [np.asarray(f.camera.K, dtype=np.float64).tolist() for f in frames]
    return Photos([Path(f.image) for f in frames], intr, Ks, spread=True)


def _cli_command(photos: list[Path], intr: Path, work: Path, quality: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "macsplat_cli",
        "reconstruct",
        *map(str, photos),
        "-o",
        str(work / "out.ply"),
        "--intrinsics",
        str(intr),
        "--report",
        str(work / "r.json"),
        "--quality",
        quality,
        "-q",
    ]


_RUSAGE_HELPER = (
    "import resource, subprocess, sys\n"
    "rc = subprocess.run(sys.argv[1:]).returncode\n"
    "u = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
    "print('MAXRSS_KB', u.ru_maxrss, 'CPU_S', u.ru_utime + u.ru_stime, file=sys.stderr)\n"
    "sys.exit(rc)\n"
)


def run_cli(
    photos: list[Path], intr: Path, work: Path, quality: str = "balanced"
) -> tuple[int, float, int, float | None, str]:
    """(return code, wall s, peak RSS bytes, CPU s, stderr) of the CLI on ``photos`` in a fresh process."""
    cmd = _cli_command(photos, intr, work, quality)
    if TIME.exists():
        wrapped = [str(TIME), "-v", *cmd]
        rss_pattern = r"Maximum resident set size \(kbytes\):\s*(\d+)"
        cpu_patterns = [r"User time \(seconds\):\s*([\d.]+)", r"System time \(seconds\):\s*([\d.]+)"]
    else:  # a fresh helper per run: RUSAGE_CHILDREN is the peak of its only child
        wrapped = [sys.executable, "-c", _RUSAGE_HELPER, *cmd]
        rss_pattern, cpu_patterns = r"MAXRSS_KB (\d+)", [r"CPU_S ([\d.]+)"]
    t0 = time.perf_counter()
    proc = subprocess.run(wrapped, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    m = re.search(rss_pattern, proc.stderr)
    cpu = [re.search(c, proc.stderr) for c in cpu_patterns]
    cpu_s = sum(float(c.group(1)) for c in cpu if c) if all(cpu) else None
    return proc.returncode, wall, int(m.group(1)) * 1024 if m else 0, cpu_s, proc.stderr


def _cli_error(stderr: str) -> str:
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip() and not ln.startswith("\t")]
    lines = [ln for ln in lines if not ln.startswith("Command ")]
    return " ".join(lines)[-300:]


def measure(photos: Photos, n: int, work: Path, colmap: bool, quality: str = "balanced") -> SizeResult:
    """The CLI (and the peer) on the first ``n`` photos."""
    chosen = photos.chosen(n)
    paths = [photos.paths[i] for i in chosen]
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    load = os.getloadavg()[0]
    rc, wall, rss, cpu_s, stderr = run_cli(paths, photos.intrinsics, work, quality)
    report_path = work / "r.json"
    report = json.loads(report_path.read_text()) if rc == 0 and report_path.exists() else {}
    if report:
        mv = report.get("multiview")
        registered = int(mv["registered"]) if mv else 2  # two photos: the two-view path, both posed or refused
        res = SizeResult(
            n,
            True,
            wall,
            rss,
            dict(report.get("times_s", {})),
            registered,
            load,
            cpu_s=cpu_s,
            extra={"gaussians": report.get("gaussians_written", report.get("gaussians"))},
        )
        if mv:
            res.extra["pairs_matched"] = len(mv.get("pairs", []))
            res.extra["pairs_accepted"] = sum(bool(p.get("accepted")) for p in mv.get("pairs", []))
            res.extra["depth_pairs"] = len(mv.get("depth_pairs", []))
            res.extra["points"] = mv.get("points")
            res.extra["reprojection_rms_px"] = mv.get("reprojection_rms_px")
    else:
        res = SizeResult(n, False, wall, rss, {}, 0, load, error=f"rc {rc}: {_cli_error(stderr)}")
    if colmap:
        import numpy as np

        from benchmarks._colmap_peer import run_colmap

        Ks = [np.asarray(photos.K[i], dtype=np.float64) for i in chosen]
        peer = run_colmap(paths, K=Ks, max_image_size=512, threads=2)
        res.colmap_s, res.colmap_registered, res.colmap_error = peer.seconds, peer.n_registered, peer.error
    return res


def _f(x: float | None, digits: int = 2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _stage_cells(r: SizeResult) -> list[float | None]:
    """The :data:`STAGES` columns, then 'other' (the report's total less the stages), then the total."""
    t = dict(r.times_s)
    if "pairs" not in t and any(k in t for k in TWO_VIEW_PAIR):
        t["pairs"] = sum(t.pop(k, 0.0) for k in TWO_VIEW_PAIR)
    stages = [t.get(s) for s in STAGES]
    total = t.get("total")
    other = None if total is None else total - sum(v for v in stages if v is not None)
    return [*stages, other, total]


def print_table(results: list[SizeResult], peer: bool) -> None:
    """The Markdown table of ``results`` (N ascending)."""
    cols = [
        "N",
        "registered",
        "pairs matched",
        "depth pairs",
        "wall s",
        "s / added photo",
        "CPU s",
        "CPU s / added photo",
        *(f"{s} s" for s in STAGES),
        "other s",
        "pipeline s",
        "peak RSS GB",
    ]
    aligns = "r" * len(cols)
    if peer:
        cols += ["COLMAP s", "COLMAP registered"]
        aligns += "rr"
    print_header(cols, aligns)
    base = next((r for r in results if r.n == 2 and r.ok), None)
    for r in sorted(results, key=lambda r: r.n):
        per = (r.wall_s - base.wall_s) / (r.n - 2) if base and r.ok and r.n > 2 else None
        cpu_per = None
        if per is not None and base is not None and r.cpu_s is not None and base.cpu_s is not None:
            cpu_per = (r.cpu_s - base.cpu_s) / (r.n - 2)
        matched = r.extra.get("pairs_matched", 1 if r.n == 2 and r.ok else None)
        accepted = r.extra.get("pairs_accepted", matched)
        pairs = "–" if matched is None else f"{accepted}/{matched}"
        dpairs = str(r.extra.get("depth_pairs", 1 if r.n == 2 and r.ok else "–"))
        cells = [
            str(r.n),
            f"{r.registered}/{r.n}" if r.ok else "failed",
            pairs,
            dpairs,
            _f(r.wall_s, 1),
            _f(per),
            _f(r.cpu_s, 1),
            _f(cpu_per),
            *(_f(v) for v in _stage_cells(r)),
            _f(r.peak_rss_bytes / GB),
        ]
        if peer:
            reg = "–" if r.colmap_registered is None else f"{r.colmap_registered}/{r.n}"
            cells += [_f(r.colmap_s, 1), reg]
        print(row(cells))
    for r in results:
        if not r.ok:
            print(f"\nN = {r.n} failed: {r.error}")
        if r.colmap_error:
            print(f"\nN = {r.n}, COLMAP: {r.colmap_error}")
    loads = ", ".join(f"N={r.n}: {r.load_before:.2f}" for r in results)
    print(f"\n1-minute load average before each run: {loads}")


def _sizes(text: str) -> list[int]:
    sizes = sorted({int(s) for s in text.split(",") if s.strip()})
    if not sizes or sizes[0] < 2:
        raise SystemExit(f"--sizes {text!r}: at least one size, each >= 2")
    return sizes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=_sizes, help="comma-separated N (default 2,4,8,16,32; --real: 2,4,8,16,20)")
    ap.add_argument("--step", type=float, default=4.0, help="degrees between neighbouring photos on the orbit")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="where the photos and results are kept")
    ap.add_argument("--no-colmap", action="store_true", help="skip the pycolmap peer")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed N = 3 run that compiles the kernels")
    ap.add_argument("--table", action="store_true", help="reprint the last run's table (<cache>/results.json)")
    ap.add_argument("--real", choices=REAL_SCENES, help="real photos instead of the orbit (N evenly spaced)")
    ap.add_argument("--data", type=Path, default=Path("../shared/data"), help="the shared data folder (--real)")
    ap.add_argument("--quality", choices=("fast", "balanced", "best"), default="balanced", help="the CLI's --quality")
    args = ap.parse_args()
    sizes = args.sizes or (REAL_SIZES if args.real else [2, 4, 8, 16, 32])
    tag = "".join(f"_{t}" for t in (args.real, None if args.quality == "balanced" else args.quality) if t)
    results_path = args.cache / f"results{tag}.json"
    if args.table:
        saved = json.loads(results_path.read_text())
        print_table([SizeResult(**r) for r in saved["results"]], saved["peer"])
        return
    from benchmarks._colmap_peer import colmap_available

    peer = not args.no_colmap and colmap_available()
    if args.real is None:
        photos = render_photos(args.cache, max(max(sizes), 3), args.step)
    else:
        photos = real_photos(args.cache, args.data, args.real)
        if max(sizes) > len(photos.paths):
            raise SystemExit(f"--sizes: {args.real} has {len(photos.paths)} photos")
    work = args.cache / f"work{tag}"
    if not args.no_warmup:
        (args.cache / "warmup").mkdir(parents=True, exist_ok=True)
        warm = [photos.paths[i] for i in photos.chosen(3)]
        rc, wall, _, _, stderr = run_cli(warm, photos.intrinsics, args.cache / "warmup")
        print(
            f"warm-up (N = 3): {wall:.1f} s" + ("" if rc == 0 else f", failed: {_cli_error(stderr)}"), file=sys.stderr
        )
    results = []
    for n in sizes:
        r = measure(photos, n, work / f"n{n}", peer, args.quality)
        results.append(r)
        peer_line = f", COLMAP {r.colmap_s:.1f} s {r.colmap_registered}/{n}" if peer and r.colmap_s is not None else ""
        print(
            f"N = {n}: {'ok' if r.ok else 'FAILED'} {r.wall_s:.1f} s, {r.peak_rss_bytes / GB:.2f} GB, "
            f"registered {r.registered}, load {r.load_before:.2f}{peer_line}",
            file=sys.stderr,
            flush=True,
        )
        results_path.write_text(json.dumps({"peer": peer, "results": [asdict(x) for x in results]}, indent=1))
    print_table(results, peer)


if __name__ == "__main__":
    main()
