"""A depth ``.npy`` that does not hold numbers (issue 37, D1): the data set is refused when it is loaded, naming the
file (``eval`` used to crash with "ValueError: could not convert string to float", no file named; ``train`` shares
the loader and is tested in ``tests/training/test_hostile_train.py``)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.datasets import load_dataset, read_depth
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import DatasetError

from support.cli import one_error_line, run_captured

W, H = 96, 64
NOT_NUMBERS = {
    "strings": lambda: np.full((H, W), "x", dtype="<U1"),
    "bytes": lambda: np.full((H, W), b"1.5", dtype="S3"),
    "complex": lambda: np.ones((H, W), np.complex64),
    "booleans": lambda: np.ones((H, W), bool),
    "records": lambda: np.zeros((H, W), [("depth", "<f4"), ("valid", "u1")]),
}


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generic-layout room of 4 posed views with depth (read only: copy it)."""
    root = tmp_path_factory.mktemp("depth_room") / "room"
    scene = syn.make_scene("room", 1)
    cams = syn.orbit_cameras(scene, [0.0, 5.0, 10.0, 15.0], width=W, height=H)
    syn.write_dataset(root, scene, [dataclasses.replace(c, name=f"f{i}") for i, c in enumerate(cams)], supersample=1)
    return root


def _with_npy_depth(room: Path, tmp_path: Path, make: object) -> tuple[Path, Path]:
    """A copy of ``room`` whose first depth map is a ``.npy`` of ``make()`` (the others stay numeric); (root, file)."""
    root = tmp_path / "room"
    shutil.copytree(room, root)
    first = sorted((root / "depth").glob("*.png"))[0]
    first.unlink()
    npy = first.with_suffix(".npy")
    np.save(npy, make())  # type: ignore[operator]
    return root, npy


def test_a_float_npy_depth_is_read(room: Path, tmp_path: Path) -> None:
    """The loader reads a numeric ``.npy`` depth: what the tests below change is only its dtype."""
    root, npy = _with_npy_depth(room, tmp_path, lambda: np.full((H, W), 2.5, np.float32))
    assert len(load_dataset(root).scenes[0].frames) == 4
    assert np.all(read_depth(npy) == 2.5)


@pytest.mark.parametrize("kind", list(NOT_NUMBERS))
def test_a_depth_npy_of_non_numbers_is_refused_naming_the_file(room: Path, tmp_path: Path, kind: str) -> None:
    root, npy = _with_npy_depth(room, tmp_path, NOT_NUMBERS[kind])
    with pytest.raises(DatasetError, match="not a numeric depth map") as e:
        load_dataset(root)
    assert str(npy) in str(e.value)
    with pytest.raises(DatasetError, match="not a numeric depth map"):
        read_depth(npy)


def test_eval_refuses_a_depth_npy_of_strings_with_exit_2(
    capsys: pytest.CaptureFixture[str], room: Path, tmp_path: Path
) -> None:
    root, npy = _with_npy_depth(room, tmp_path, NOT_NUMBERS["strings"])
    code, _, err = run_captured(capsys, "eval", "--data", root, "--size", "64", "--max-pairs", "1", "--max-targets",
                                "1", "--no-baselines", "-q", "--out", tmp_path / "out")  # fmt: skip
    line = one_error_line(err)
    assert code == 2 and str(npy) in line and "dtype <U1" in line, err
