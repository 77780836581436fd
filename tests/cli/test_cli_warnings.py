"""Python warnings of the libraries underneath (Pillow, NumPy, torch) never reach the terminal as raw text: a
command prints its own lines only; ``--verbose`` shows each warning as one DEBUG line."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from support.scenes import PairSpec, rendered_pair

# An EXIF block whose directory points past its end: Pillow warns "Corrupt EXIF data" and "Tag data larger than
# file" while reading the orientation, and still decodes the pixels.
_BAD_EXIF = (
    b"Exif\x00\x00II*\x00\x08\x00\x00\x00\x05\x00"
    b"\x12\x01\x03\x00\x01\x00\x00\x00\x01\x00\x00\x00"
    b"\x0f\x01\x02\x00\xff\xff\x00\x00\x00\x10\x00\x00"
)


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A textured room pair 12° apart at 128×96, both JPEGs with a corrupt EXIF block."""
    folder = tmp_path_factory.mktemp("warn_pair")
    paths = []
    for i, image in enumerate(rendered_pair(PairSpec("room", 12.0, (128, 96), 60.0, scene_seed=5)).images):
        pixels = (np.clip(image, 0, 1) * 255).round().astype(np.uint8)
        path = folder / f"v{i}.jpg"
        Image.fromarray(pixels).save(path, quality=95, exif=_BAD_EXIF)
        paths.append(path)
    return paths[0], paths[1]


def _reconstruct(pair: tuple[Path, Path], out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-W", "default", "-m", "macsplat_cli", "reconstruct", str(pair[0]), str(pair[1])]
    cmd += ["-o", str(out / "s.ply"), "--size", "128", "--accept-low-confidence", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def test_library_warnings_are_not_printed_raw(pair: tuple[Path, Path], tmp_path: Path) -> None:
    with warnings.catch_warnings(record=True) as seen:  # the input really makes Pillow warn
        warnings.simplefilter("always")
        with Image.open(pair[0]) as im:
            im.getexif()
    assert any("EXIF" in str(w.message) for w in seen)
    done = _reconstruct(pair, tmp_path, "-q")
    assert "Warning" not in done.stderr and "warnings.warn" not in done.stderr, done.stderr
    verbose = _reconstruct(pair, tmp_path, "--verbose")
    lines = [ln for ln in verbose.stderr.splitlines() if "UserWarning from" in ln]
    assert lines and all("EXIF" in ln or "Tag data" in ln for ln in lines), verbose.stderr
    assert "warnings.warn" not in verbose.stderr
