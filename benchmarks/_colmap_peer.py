"""The peer for the N-photo benchmark: pycolmap's own incremental SfM (its SIFT, its matching, its mapper) on the
same photos, so that our poses can be set side by side with COLMAP's.

pycolmap is optional (not in CI): :func:`colmap_available` says whether it can be imported, and :func:`run_colmap`
reports its absence in :attr:`ColmapRun.error` instead of raising. Written against pycolmap 4.2.1 (COLMAP 4 API:
``Database.open``, rigs/frames, ``Image.cam_from_world()`` a method).

What :func:`run_colmap` sets, everything else left at COLMAP's defaults:

* the photos are symlinked into a work folder as ``0000.jpg``, ``0001.png``, ... (unique, and COLMAP's sorted
  order is the input order; the original suffix is kept for the image reader);
* SIFT extraction with ``max_image_size`` (512: our working size), on the CPU, ``threads`` threads. COLMAP reads the
  original files: the camera's width/height are the photo's own and the keypoints are scaled back to it (checked
  on CO3D: 1066 x 1896 camera, keypoints up to x 1061, y 1890 with ``max_image_size=512``), so every K it returns
  is at the photo's original resolution;
* exhaustive matching (default ratio test, cross check, RANSAC verification), CPU, ``threads`` threads;
* incremental mapping with ``num_threads = threads``, ``min_model_size = 2`` (the default 10 would discard every
  model of fewer than 10 photos) and, if ``seed`` is given, the mapper's and the verification RANSAC's seed;
* with known K: one PINHOLE camera per photo with those intrinsics as a prior (``has_prior_focal_length``) and held
  fixed: ``ba_refine_focal_length``, ``ba_refine_principal_point``, ``ba_refine_extra_params``,
  ``mapper.abs_pose_refine_focal_length`` and ``mapper.abs_pose_refine_extra_params`` all off;
* without K: SIMPLE_RADIAL (f, cx, cy, k) with COLMAP's default prior (EXIF focal length if present, else
  f = 1.2 x the long side, principal point at the centre), one camera shared by all photos when
  ``single_camera``, else one per photo. The radial term ``k`` is not in the returned K (it is in
  :attr:`ColmapRun.camera_params`).

Conventions: COLMAP's image origin is the top-left corner of the top-left pixel (pixel centres at +0.5), the same
as macsplat's, so its K is returned unchanged; its ``cam_from_world`` is OpenCV-axed world-to-camera, returned
inverted as cam-to-world in COLMAP's own (arbitrary similarity) world frame.

Self-check (needs pycolmap and the shared data): ``python -m benchmarks._colmap_peer [--data /work/shared/data]``.
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from macsplat_cli.metrics import rotation_error_deg


@dataclass
class ColmapRun:
    """What COLMAP made of N photos, per photo in input order."""

    registered: list[bool]
    """Whether the photo has a pose in the largest model."""
    cam_to_world: list[np.ndarray | None]
    """[4, 4] float64 per photo, OpenCV axes, COLMAP's world frame (None if unregistered)."""
    K: list[np.ndarray | None]
    """[3, 3] float64 per photo at the photo's original resolution, pixel centres at +0.5 (None if unregistered)."""
    seconds: float
    """Extraction + matching + mapping wall time (not the symlinking or reading back)."""
    n_models: int
    """Reconstructions the mapper produced; the largest (most registered photos) is the one reported."""
    error: str | None
    """Why it failed (no model, pycolmap missing, an exception), else None."""
    camera_model: list[str | None] = field(default_factory=list)
    """COLMAP's camera model name per photo (None if unregistered)."""
    camera_params: list[np.ndarray | None] = field(default_factory=list)
    """COLMAP's raw camera parameters per photo, e.g. SIMPLE_RADIAL ``[f, cx, cy, k]`` (None if unregistered)."""
    sizes: list[tuple[int, int] | None] = field(default_factory=list)
    """(width, height) at which COLMAP read each photo (None if unregistered)."""

    @property
    def n_registered(self) -> int:
        """How many photos have a pose."""
        return sum(self.registered)


def colmap_available() -> bool:
    """Whether pycolmap can be imported."""
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        return False
    return True


def _empty(n: int, seconds: float, n_models: int, error: str | None) -> ColmapRun:
    """No photo registered."""
    return ColmapRun([False] * n, [None] * n, [None] * n, seconds, n_models, error, [None] * n, [None] * n, [None] * n)


def _stage_photos(paths: Sequence[Path], images: Path) -> list[str]:
    """Symlink the photos into ``images`` under order-preserving unique names; the names, in input order."""
    images.mkdir(parents=True, exist_ok=True)
    width = max(4, len(str(len(paths))))
    names = []
    for i, p in enumerate(paths):
        name = f"{i:0{width}d}{Path(p).suffix.lower()}"
        (images / name).symlink_to(Path(p).resolve())
        names.append(name)
    return names


def _known_intrinsics(pycolmap: Any, db_path: Path, names: list[str], K: Sequence[np.ndarray]) -> None:
    """Write each photo's K into its PINHOLE camera in the database (one camera per photo), as a prior."""
    with pycolmap.Database.open(db_path) as db:
        by_name = {im.name: im for im in db.read_all_images()}
        for name, k in zip(names, K, strict=True):
            if name not in by_name:  # the reader skipped it (unreadable): it stays unregistered
                continue
            cam = db.read_camera(by_name[name].camera_id)
            k = np.asarray(k, dtype=np.float64)
            cam.params = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
            cam.has_prior_focal_length = True
            db.update_camera(cam)


def _pipeline_options(pycolmap: Any, threads: int, fixed_K: bool, seed: int | None) -> Any:
    po = pycolmap.IncrementalPipelineOptions()
    po.num_threads = threads
    po.min_model_size = 2  # default 10 drops every model smaller than 10 photos
    if seed is not None:
        po.random_seed = seed
    if fixed_K:
        po.ba_refine_focal_length = False
        po.ba_refine_principal_point = False
        po.ba_refine_extra_params = False
        po.mapper.abs_pose_refine_focal_length = False
        po.mapper.abs_pose_refine_extra_params = False
    return po


def _sfm(
    pycolmap: Any,
    work: Path,
    names: list[str],
    K: Sequence[np.ndarray] | None,
    max_image_size: int,
    single_camera: bool,
    threads: int,
    seed: int | None,
) -> dict[int, Any]:
    """Extraction, exhaustive matching and incremental mapping in ``work``; the mapper's models."""
    db_path, images, sparse = work / "database.db", work / "images", work / "sparse"
    reader = pycolmap.ImageReaderOptions()
    if K is None:
        reader.camera_model = "SIMPLE_RADIAL"
        mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    else:
        reader.camera_model = "PINHOLE"
        mode = pycolmap.CameraMode.PER_IMAGE  # K may differ per photo; fixed intrinsics make sharing moot
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.num_threads = threads
    pycolmap.extract_features(
        db_path,
        images,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    if K is not None:
        _known_intrinsics(pycolmap, db_path, names, K)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    verification = pycolmap.TwoViewGeometryOptions()
    if seed is not None:
        verification.ransac.random_seed = seed
    pycolmap.match_exhaustive(
        db_path, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
    )
    sparse.mkdir(parents=True, exist_ok=True)
    options = _pipeline_options(pycolmap, threads, K is not None, seed)
    return dict(pycolmap.incremental_mapping(db_path, images, sparse, options=options))


def _verified_pairs(pycolmap: Any, work: Path, n: int) -> str:
    """How many of the n(n-1)/2 pairs passed COLMAP's geometric verification, and the best one's inliers."""
    with pycolmap.Database.open(work / "database.db") as db:
        inliers = [len(g.inlier_matches) for g in db.read_two_view_geometries()[1]]
    best = max(inliers, default=0)
    return f"{sum(1 for k in inliers if k > 0)} of {n * (n - 1) // 2} pairs verified, best {best} inliers"


def _read_model(rec: Any, names: list[str], seconds: float, n_models: int) -> ColmapRun:
    """The per-photo poses and intrinsics of one reconstruction, in input order."""
    index = {name: i for i, name in enumerate(names)}
    n = len(names)
    run = _empty(n, seconds, n_models, None)
    for image in rec.images.values():
        if not image.has_pose:
            continue
        i = index[image.name]
        w2c = np.eye(4)
        w2c[:3, :] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        cam = image.camera
        run.registered[i] = True
        run.cam_to_world[i] = np.linalg.inv(w2c)
        run.K[i] = np.asarray(cam.calibration_matrix(), dtype=np.float64)
        run.camera_model[i] = str(cam.model_name)
        run.camera_params[i] = np.asarray(cam.params, dtype=np.float64).copy()
        run.sizes[i] = (int(cam.width), int(cam.height))
    return run


def run_colmap(
    paths: Sequence[Path],
    *,
    K: Sequence[np.ndarray] | None = None,
    max_image_size: int = 512,
    single_camera: bool = True,
    workdir: Path | None = None,
    threads: int = 2,
    seed: int | None = 0,
    verbose: bool = False,
) -> ColmapRun:
    """COLMAP's incremental SfM on ``paths`` (options: the module docstring).

    ``K``: one [3, 3] per photo at its original resolution (+0.5 pixel centres), held fixed; None lets COLMAP
    estimate SIMPLE_RADIAL intrinsics. ``workdir``: where the database, the symlinked photos and the models go
    (created; a previous run's database there is removed); None uses a temporary folder, deleted afterwards.
    ``seed``: the mapper's and RANSAC's random seed (None: COLMAP's default, random); with ``threads > 1`` runs
    may still differ. ``verbose``: keep COLMAP's INFO log on stderr.
    """
    n = len(paths)
    if K is not None and len(K) != n:
        raise ValueError(f"K: {len(K)} matrices for {n} photos")
    try:
        import pycolmap
    except ImportError as exc:
        return _empty(n, 0.0, 0, f"pycolmap is not installed ({exc})")
    with tempfile.TemporaryDirectory(prefix="colmap_peer_") as tmp:
        work = Path(tmp) if workdir is None else Path(workdir)
        work.mkdir(parents=True, exist_ok=True)
        for stale in ("database.db", "images", "sparse"):
            target = work / stale
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
        names = _stage_photos(paths, work / "images")
        level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = level if verbose else max(level, int(pycolmap.logging.Level.WARNING.value))
        if seed is not None:
            pycolmap.set_random_seed(seed)
        t0 = time.perf_counter()
        try:
            models = _sfm(pycolmap, work, names, K, max_image_size, single_camera, threads, seed)
        except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError; report, don't crash the table
            return _empty(n, time.perf_counter() - t0, 0, f"{type(exc).__name__}: {exc}")
        finally:
            pycolmap.logging.minloglevel = level
        seconds = time.perf_counter() - t0
        if not models:
            return _empty(n, seconds, 0, f"the mapper made no model ({_verified_pairs(pycolmap, work, n)})")
        largest = max(models.values(), key=lambda r: r.num_reg_images())
        return _read_model(largest, names, seconds, len(models))


def align_rotation_errors(est: Sequence[np.ndarray | None], gt: Sequence[np.ndarray]) -> np.ndarray:
    """Relative-rotation errors, degrees, for every pair i < j of photos both registered (``est`` not None).

    ``est``, ``gt``: cam-to-world [4, 4] (or [3, 3] rotations) per photo, in the same order. The error of a pair is
    the angle of ``(R_iᵀ R_j)_estᵀ (R_iᵀ R_j)_gt``; ``R_iᵀ R_j`` (camera j's axes in camera i's) does not depend on
    the world frame, so no alignment is needed and any global rotation (and scale, and translation) of either
    reconstruction leaves the errors unchanged. Pairs in ``itertools.combinations`` order; empty if fewer than two
    photos are registered. [P] float64
    """
    if len(est) != len(gt):
        raise ValueError(f"{len(est)} estimated poses for {len(gt)} ground-truth ones")
    idx = [i for i, e in enumerate(est) if e is not None]
    out = []
    for i, j in itertools.combinations(idx, 2):
        ei, ej = np.asarray(est[i], dtype=np.float64)[:3, :3], np.asarray(est[j], dtype=np.float64)[:3, :3]
        gi, gj = np.asarray(gt[i], dtype=np.float64)[:3, :3], np.asarray(gt[j], dtype=np.float64)[:3, :3]
        out.append(rotation_error_deg(ei.T @ ej, gi.T @ gj))
    return np.asarray(out, dtype=np.float64)


def focal_errors_pct(est: Sequence[np.ndarray | None], gt: Sequence[np.ndarray]) -> np.ndarray:
    """|f_est / f_gt - 1| x 100 per registered photo, f = sqrt(fx fy) of each [3, 3] K (COLMAP's SIMPLE_RADIAL
    has one f; the ground truth may have fx != fy). [R] float64"""
    f = [np.sqrt(abs(k[0, 0] * k[1, 1])) for k in gt]
    return np.asarray(
        [abs(np.sqrt(e[0, 0] * e[1, 1]) / f[i] - 1.0) * 100.0 for i, e in enumerate(est) if e is not None],
        dtype=np.float64,
    )


# ---------------------------------------------------------------------------------------------------------------
# Self-check


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _check_gauge_freedom() -> None:
    """``align_rotation_errors`` is zero under a similarity of the world and sees a perturbation of one camera."""
    rng = np.random.default_rng(0)
    gt = []
    for _ in range(5):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _random_rotation(rng), rng.normal(size=3)
        gt.append(T)
    Rs, ts = _random_rotation(rng), rng.normal(size=3)
    moved: list[np.ndarray] = []
    for T in gt:  # the same cameras in another world frame: x_new = 3 Rs x + ts
        E = np.eye(4)
        E[:3, :3], E[:3, 3] = Rs @ T[:3, :3], 3.0 * Rs @ T[:3, 3] + ts
        moved.append(E)
    err = align_rotation_errors(moved, gt)
    assert err.shape == (10,) and err.max() < 1e-6, err  # round-off of a few 3x3 products: ~1e-13° (atan2 form)
    a = np.radians(2.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    moved[2][:3, :3] = moved[2][:3, :3] @ Rz  # camera 2 turned 2° about its own axis
    est: list[np.ndarray | None] = [*moved[:4], None]
    err = align_rotation_errors(est, gt)
    assert err.shape == (6,), err.shape  # pairs among {0, 1, 2, 3}
    assert np.allclose(np.sort(err), [0, 0, 0, 2, 2, 2], atol=1e-6), err


def _cases(data: Path) -> list[tuple[str, str, list[int]]]:
    co3d = [("co3d", f"co3d {n}", np.linspace(0, 19, n).round().astype(int).tolist()) for n in (3, 5, 8, 20)]
    return co3d + [("icl_livingroom", "icl 5", list(range(5)))]


def _row(label: str, with_K: bool, n: int, run: ColmapRun, gt_c2w: list[np.ndarray], gt_K: list[np.ndarray]) -> str:
    from benchmarks._common import row

    rot = align_rotation_errors(run.cam_to_world, gt_c2w)
    focal = focal_errors_pct(run.K, gt_K)
    med, mx = (f"{np.median(rot):.2f}", f"{rot.max():.2f}") if rot.size else ("–", "–")
    fe = "fixed" if with_K else (f"{np.median(focal):.1f}" if focal.size else "–")
    note = run.error or (f"{run.n_models} models" if run.n_models > 1 else "")
    return row(
        [label, "yes" if with_K else "no", str(n), f"{run.n_registered}/{n}", med, mx, fe, f"{run.seconds:.1f}", note]
    )


def _check_run(run: ColmapRun, with_K: bool, gt_K: list[np.ndarray], sizes: list[tuple[int, int]]) -> None:
    """COLMAP read the photos at their own size, and a known K came back unchanged."""
    for i, reg in enumerate(run.registered):
        if not reg:
            continue
        assert run.sizes[i] == sizes[i], (i, run.sizes[i], sizes[i])
        c2w = run.cam_to_world[i]
        assert c2w is not None and np.allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-9)
        if with_K:
            K = run.K[i]
            assert K is not None and np.allclose(K, gt_K[i], rtol=1e-9), (K, gt_K[i])


def main(argv: Sequence[str] | None = None) -> None:
    from benchmarks._common import print_header, progress
    from benchmarks._dev import dev_frames

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("/work/shared/data"), help="the shared data folder")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    _check_gauge_freedom()
    if not colmap_available():
        raise SystemExit("pycolmap is not installed: only the synthetic check ran")
    import pycolmap

    progress(f"pycolmap {pycolmap.__version__}, {args.threads} threads, max_image_size 512")
    print_header(
        [
            "scene",
            "known K",
            "photos",
            "registered",
            "median rel. rot. err °",
            "max rel. rot. err °",
            "focal err % (median)",
            "seconds",
            "note",
        ],
        "llrrrrrrl",
    )
    for scene, label, idx in _cases(args.data):
        frames = [dev_frames(args.data, scene)[i] for i in idx]
        gt_c2w = [f.camera.cam_to_world for f in frames]
        gt_K = [f.camera.K for f in frames]
        sizes = [(f.camera.width, f.camera.height) for f in frames]
        for with_K in (True, False):
            run = run_colmap([f.image for f in frames], K=gt_K if with_K else None, threads=args.threads)
            _check_run(run, with_K, gt_K, sizes)
            print(_row(label, with_K, len(frames), run, gt_c2w, gt_K), flush=True)


if __name__ == "__main__":
    main()
