"""The same photos and options give the same scene: byte for byte on one machine, to a stated tolerance across
CPU kernel sets.

Each run is a fresh ``macsplat reconstruct`` process, since the thread counts (``OMP_NUM_THREADS``,
``NUMBA_NUM_THREADS``) and the kernel sets (``ATEN_CPU_CAPABILITY``, ``MKL_ENABLE_INSTRUCTIONS``) are read once,
when torch, MKL and Numba start.

Across kernel sets the arithmetic is the same but its order is not (vector widths, blocked reductions), so results
differ by rounding: the pose within ``POSE_TOL_DEG``, the Gaussians within ``GAUSSIAN_RTOL`` and what they draw within
``RENDER_MIN_PSNR`` of each other.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.cameras import CameraSet, load_cameras, save_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.images import save_image
from macsplat_cli.ply import read_ply
from macsplat_cli.render import render_camera

# Tolerances between two kernel sets. The pose is refined by Levenberg–Marquardt to its optimum, where a rounding
# change of the inputs (~1e-7 relative, float32 descriptors and depths) moves it by far less than this; the bound
# is 1000× what was measured (≤ 1e-6°) so that a different matching decision on another CPU still passes while a
# pose estimated from other evidence does not.
POSE_TOL_DEG = 1e-3
# The Gaussians: every attribute within 1e-5 of its largest magnitude (float32 rounding is 6e-8 relative; the
# stages between the photos and the PLY amplify it a few times: measured ≤ 1 ulp of the largest value).
GAUSSIAN_RTOL = 1e-5
# What they draw: a splat renderer sorts by depth, and the two views' Gaussians on one surface lie at nearly equal
# depths, so a rounding-level change reorders them (jittering the means by 1e-6 alone costs 38–40 dB here): 30 dB
# (an RMS error of 3 % of the colour range) separates that from a different scene.
RENDER_MIN_PSNR = 30.0
# Thread counts a user's machine may run with, and kernel sets other than the machine's own.
THREADS = [{"OMP_NUM_THREADS": "1"}, {"OMP_NUM_THREADS": "2"}, {"OMP_NUM_THREADS": "2", "NUMBA_NUM_THREADS": "1"}]
KERNEL_SETS = {
    "portable": {"ATEN_CPU_CAPABILITY": "default", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"},
    "avx2": {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"},
}
_KERNEL_VARS = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS")


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A ray-traced object pair 20° apart, 320×240, with its true intrinsics."""
    folder = tmp_path_factory.mktemp("determinism")
    scene = syn.make_scene("object", 0)
    cams = syn.orbit_pair(scene, 20.0, width=320, height=240, names=("a", "b"))
    for cam in cams:
        save_image(folder / f"{cam.name}.png", syn.render(scene, cam).image)
    save_cameras(folder / "cameras.json", CameraSet(list(cams)))
    return folder / "a.png", folder / "b.png", folder / "cameras.json"


Run = Callable[[str, dict[str, str]], tuple[bytes, bytes]]


@pytest.fixture(scope="module")
def run(pair: tuple[Path, Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Run:
    """``run(key, env)``: one ``macsplat reconstruct`` process under ``env`` (cached by ``key``), into the folder
    ``<tmp>/<key>``; returns (PLY bytes, cameras bytes)."""
    root = tmp_path_factory.mktemp("runs")
    cache: dict[str, tuple[bytes, bytes]] = {}

    def get(key: str, env: dict[str, str]) -> tuple[bytes, bytes]:
        if key not in cache:
            a, b, intrinsics = pair
            out = root / key
            out.mkdir()
            full = {k: v for k, v in os.environ.items() if k not in _KERNEL_VARS} | env
            cmd = [sys.executable, "-m", "macsplat_cli", "reconstruct", str(a), str(b), "-o", str(out / "s.ply")]
            cmd += ["--intrinsics", str(intrinsics), "--size", "256"]
            done = subprocess.run(cmd, env=full, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, done.stderr
            cache[key] = (out / "s.ply").read_bytes(), (out / "s.cameras.json").read_bytes()
        return cache[key]

    get.root = root  # type: ignore[attr-defined]
    return get


def test_same_bytes_whatever_the_thread_count(run: Run) -> None:
    """Run after run and whatever the thread counts, the PLY and the cameras file are byte-identical."""
    first = run("threads0", THREADS[0])
    for i, env in enumerate(THREADS[1:], 1):
        assert run(f"threads{i}", env) == first, f"the outputs differ under {env}"
    assert run("threads0-again", THREADS[0]) == first, "the outputs differ from one run to the next"


def _rotation_gap_deg(R0: np.ndarray, R1: np.ndarray) -> float:
    c = (np.trace(R0.T @ R1) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@pytest.mark.parametrize("kernels", ["portable", "avx2"])
def test_other_kernel_set_agrees_to_the_stated_tolerance(run: Run, kernels: str) -> None:
    """Other kernel sets (portable: no AVX, SSE4.2 MKL; AVX2, the common laptop) give the same pose and the same
    scene to rounding."""
    runs = {}
    for key, env in (("threads1", THREADS[1]), (kernels, THREADS[1] | KERNEL_SETS[kernels])):
        run(key, env)
        folder = run.root / key  # type: ignore[attr-defined]
        runs[key] = (load_cameras(folder / "s.cameras.json"), read_ply(folder / "s.ply"))
    (cams0, g0), (cams1, g1) = runs["threads1"], runs[kernels]
    c0, c1 = cams0[1], cams1[1]
    assert _rotation_gap_deg(c0.cam_to_world[:3, :3], c1.cam_to_world[:3, :3]) <= POSE_TOL_DEG
    t0, t1 = c0.cam_to_world[:3, 3], c1.cam_to_world[:3, 3]  # unit baselines: the gap is an angle in radians
    assert np.degrees(np.linalg.norm(t0 - t1)) <= POSE_TOL_DEG
    # A merge decision of the compaction may flip on a rounding tie: the counts may differ by a few.
    assert abs(len(g0) - len(g1)) <= 0.001 * len(g0)
    if len(g0) == len(g1):
        for name, x, y in (
            ("means", g0.means, g1.means),
            ("covariances", g0.covariances(), g1.covariances()),  # quaternions of round Gaussians are arbitrary
            ("opacities", g0.opacities, g1.opacities),
            ("sh", g0.sh, g1.sh),
        ):
            gap = float((x - y).abs().max())
            assert gap <= GAUSSIAN_RTOL * float(x.abs().max()), f"{name}: the kernel sets differ by {gap:.3g}"
    for cam in (cams0[0], c0, _between(cams0[0], c0)):
        im0 = render_camera(g0, cam).rgb.clamp(0, 1)
        im1 = render_camera(g1, cam).rgb.clamp(0, 1)
        mse = float(torch.mean((im0.double() - im1.double()) ** 2))
        psnr = 10 * np.log10(1.0 / max(mse, 1e-20))
        assert psnr >= RENDER_MIN_PSNR, f"{cam.name}: the two kernel sets' scenes differ ({psnr:.1f} dB)"


def _between(a, b):  # noqa: ANN001, ANN202 - cameras
    """A camera half way between two (same intrinsics, centre half way, rotation of the first)."""
    m = a.cam_to_world.copy()
    m[:3, 3] = 0.5 * (a.cam_to_world[:3, 3] + b.cam_to_world[:3, 3])
    return dataclasses.replace(a, name="between", cam_to_world=m)


def test_cameras_file_has_no_run_dependent_fields(run: Run) -> None:
    """What makes byte-identity possible: the cameras file holds no time and no path of the output folder."""
    text = run("threads1", THREADS[1])[1].decode()
    doc = json.loads(text)
    assert str(run.root) not in text  # type: ignore[attr-defined]
    assert not {"time", "seconds", "timestamp", "date"} & set(_keys(doc))


def _keys(doc: object) -> set[str]:
    if isinstance(doc, dict):
        return set(doc) | set().union(*(_keys(v) for v in doc.values()))
    if isinstance(doc, list):
        return set().union(*(_keys(v) for v in doc)) if doc else set()
    return set()
