"""eval --protocol mac-splat: the test-set rows it keeps (every 10th, the excluded scene out), and its CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macsplat_cli.errors import DatasetError
from macsplat_cli.evaluation import load_cases, load_dataset
from macsplat_cli.evaluation.protocols import PROTOCOLS
from macsplat_cli.evaluation.reconstructors import BACKENDS

from support.cli import run_captured
from support.evaluation import ORACLE


def _test_sets(folder: Path, scene: str) -> Path:
    """Two Splatt3R-style test sets: 30 rows each, the rows of an excluded scene among them."""
    folder.mkdir(parents=True, exist_ok=True)
    pairs = [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (3, 4), (2, 4), (4, 5), (3, 5), (0, 3)]
    for name in ("test_set_0.9_0.9.json", "test_set_0.5_0.5.json"):
        rows = []
        for k in range(30):
            c0, c1 = pairs[k % len(pairs)]
            t = next(f for f in range(6) if f not in (c0, c1))
            rows.append(["cc5237fd77" if k % 10 == 5 else scene, c0, c1, (t + k // 10) % 6 if k // 10 else t])
        (folder / name).write_text(json.dumps(rows))
    return folder


def test_every_10th_row_of_each_file_and_the_excluded_scene(plane: Path, tmp_path: Path) -> None:
    dataset = load_dataset(plane, "auto")
    scene = dataset.scenes[0].name
    folder = _test_sets(tmp_path / "sets", scene)
    proto = PROTOCOLS["mac-splat"]
    sel = load_cases(folder, dataset, every=proto.every_nth_row, exclude=proto.exclude_scenes)
    rows = {f.name: json.loads(f.read_text()) for f in sorted(folder.glob("*.json"))}
    expected = [(f, r) for f in sorted(rows) for r in rows[f][::10] if r[0] != "cc5237fd77"]
    assert sum(len(c.targets) for c in sel.cases) == len(expected) == 6  # rows 0, 10, 20 of each file
    assert {c.split for c in sel.cases} == {"close", "wide"}  # from the files' thresholds (0.9, 0.5)
    every = load_cases(folder, dataset, exclude=proto.exclude_scenes)
    assert sum(len(c.targets) for c in every.cases) > 3 * len(expected)  # without the protocol: all rows but 6
    with pytest.raises(DatasetError, match="cc5237fd77"):
        load_cases(folder, dataset)  # the excluded scene is not in this data set: only the protocol drops it


def test_cli_protocol_needs_the_test_sets_and_runs(capsys, plane: Path, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setitem(BACKENDS, "oracle", lambda config, models=None: ORACLE)
    code, _, err = run_captured(capsys, "eval", "--data", plane, "--protocol", "mac-splat", "--out", tmp_path / "r")
    assert code == 2 and "--protocol mac-splat evaluates published test sets: give --cases" in err
    code, _, err = run_captured(capsys, "eval", "--data", plane, "--protocol", "nope", "--out", tmp_path / "r")
    assert code == 2 and "use one of mac-splat" in err
    scene = load_dataset(plane, "auto").scenes[0].name
    folder = _test_sets(tmp_path / "sets", scene)
    code, _, err = run_captured(capsys, "eval", "--data", plane, "--protocol", "mac-splat", "--cases", folder,
                                "--backend", "oracle", "--size", "128", "--out", tmp_path / "r", "-q")  # fmt: skip
    assert code == 0, err
    doc = json.loads((tmp_path / "r" / "results.json").read_text())
    assert doc["options"]["protocol"] == "mac-splat" and sum(len(c["targets"]) for c in doc["cases"]) == 6
    row = doc["summary"][0]
    assert {"psnr_masked", "psnr_masked_rgbsum", "ssim_masked"} <= row.keys()


def test_crop_about_the_principal_point_keeps_the_projection() -> None:
    """A 3-D point projects to the same place in the crop as in the photo carried through the crop's steps."""
    import numpy as np

    from macsplat_cli.cameras import Camera
    from macsplat_cli.evaluation.crop import crop_camera

    K = np.array([[700.0, 0.0, 410.3], [0.0, 690.0, 300.8], [0.0, 0.0, 1.0]])
    cam = Camera("c", 800, 560, K, np.eye(4))
    crop, (x0, y0, x1, y1), (rw, rh), (ox, oy) = crop_camera(cam, 512)
    assert (crop.width, crop.height) == (512, 512)
    assert (x0 + x1) / 2 == pytest.approx(410.3, abs=1.0) and (y0 + y1) / 2 == pytest.approx(300.8, abs=1.0)
    assert min(rw, rh) == 512
    X = np.array([0.3, -0.2, 2.5])
    u = K @ X / X[2]
    expected = ((u[0] - x0) * rw / (x1 - x0) - ox, (u[1] - y0) * rh / (y1 - y0) - oy)
    v = crop.K @ X / X[2]
    assert v[:2] == pytest.approx(expected, abs=1e-9)
    assert crop.K[0, 2] == pytest.approx(256.0, abs=1.0) and crop.K[1, 2] == pytest.approx(256.0, abs=1.0)


def test_cli_protocol_crops_the_frames(capsys, plane: Path, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """The oracle reconstructs from the frames it is given: with the protocol they are 512x512 crops."""
    seen: list[set[int]] = []

    class Spy:
        name = "oracle"

        def __getattr__(self, attr: str):  # noqa: ANN204 - everything else is the oracle's
            return getattr(ORACLE, attr)

        def __call__(self, scene, case, settings):  # noqa: ANN001, ANN204
            seen.append(
                {d for i in case.context for d in (scene.frames[i].camera.width, scene.frames[i].camera.height)}
            )
            return ORACLE(scene, case, settings)

    monkeypatch.setitem(BACKENDS, "oracle", lambda config, models=None: Spy())
    scene = load_dataset(plane, "auto").scenes[0].name
    folder = _test_sets(tmp_path / "sets", scene)
    code, _, err = run_captured(capsys, "eval", "--data", plane, "--protocol", "mac-splat", "--cases", folder,
                                "--backend", "oracle", "--size", "128", "--out", tmp_path / "r", "-q")  # fmt: skip
    assert code == 0, err
    assert seen and all(s == {512} for s in seen)
