"""``macsplat eval`` and ``macsplat bench`` end to end, through the console-script entry point.

The fast tests register the ground-truth reconstructor as a backend (the registry is how
backends plug in); one test runs the real classical pipeline on a small synthetic room.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.datasets import synthetic as S

from support.cli import run_captured
from support.evaluation import translated_camera, write_blank_dataset, write_plane_dataset

run = run_captured


def _rows(stdout: str, method: str) -> list[dict]:
    return [r for r in json.loads(stdout)["summary"] if r["method"] == method]


def test_eval_writes_results_and_tables(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    out = tmp_path / "res"
    code, stdout, err = run(capsys, "eval", "--data", plane, "--backend", "oracle", "--out", out, "--json")
    assert code == 0, err
    assert "novel views" in err and "pose, depth, time (oracle)" in err and "AUC@5/10/20" in err
    rows = _rows(stdout, "oracle")
    assert {r["split"] for r in rows} == {"close", "medium", "wide", "very-wide", "all"}
    for r in rows:
        assert r["failed"] == 0 and r["rotation_error_deg"] < 1e-6 and r["auc@5"] == 1.0
        assert r["psnr_masked"] >= 40.0  # ground-truth geometry, over the pixels the contexts see
        assert r["depth_absrel"] < 1e-5
    assert {r["method"] for r in json.loads(stdout)["summary"]} == {"oracle", "points", "copy"}
    doc = json.loads((out / "results.json").read_text())
    assert doc["complete"] and doc["cases_done"] == doc["cases_total"] == len(doc["cases"])
    assert doc["split_modes"] == {"plane": "coverage"}
    assert (out / "coverage" / "plane.json").is_file()
    header = (out / "results.csv").read_text().splitlines()[0]
    assert header.startswith("scene,split,context_0,context_1,target,target_name,method,status,psnr,ssim")
    assert len((out / "cases.jsonl").read_text().splitlines()) == doc["cases_total"]


def test_splatt3r_compatible_masked_psnr_is_4_77_db_lower(
    capsys,  # noqa: ANN001
    plane: Path,
    tmp_path: Path,
    oracle_backend: None,
) -> None:
    args = ["eval", "--data", plane, "--backend", "oracle", "--split", "wide", "--no-baselines", "--json", "-q"]
    code, std, _ = run(capsys, *args, "--out", tmp_path / "a")
    code2, compat, _ = run(capsys, *args, "--out", tmp_path / "b", "--splatt3r-compatible")
    assert code == code2 == 0
    a, b = _rows(std, "oracle")[0], _rows(compat, "oracle")[0]
    assert a["psnr_masked"] - b["psnr_masked"] == pytest.approx(10 * math.log10(3.0), abs=1e-9)
    assert b["ssim_masked"] is None and b["psnr"] >= a["psnr"]  # masked-out pixels count as perfect
    assert _rows(std, "points") == []


def test_eval_classical_backend_end_to_end(capsys, tmp_path: Path) -> None:  # noqa: ANN001
    scene = S.room_scene(3)
    S.write_dataset(tmp_path / "room", scene, S.orbit_cameras(scene, [-8, 0, 8], width=160, height=128))
    out = tmp_path / "res"
    code, _, err = run(
        capsys, "eval", "--data", tmp_path / "room", "--size", "160", "--out", out, "--split-by", "angle"
    )
    assert code == 0, err
    doc = json.loads((out / "results.json").read_text())
    (case,) = doc["cases"]
    assert case["context"] == [0, 2] and [t["index"] for t in case["targets"]] == [1]
    assert case["split"] == "medium"  # optical axes 15.5° apart
    assert case["status"] in ("ok", "failed") and case["time_s"] > 0
    if case["status"] == "ok":
        assert case["rotation_error_deg"] < 5.0
        assert set(case["targets"][0]["metrics"]) == {"classical", "points", "copy"}


def test_eval_bad_dataset_exits_2_naming_the_file(capsys, tmp_path: Path) -> None:  # noqa: ANN001
    root = tmp_path / "bad"
    write_blank_dataset(root, [translated_camera(f"v{i}", 0.1 * i) for i in range(3)])
    (root / "images" / "v2.png").unlink()
    code, _, err = run(capsys, "eval", "--data", root, "--out", tmp_path / "res")
    assert code == 2 and "error:" in err and "v2: image not found" in err
    assert not (tmp_path / "res").exists()  # validated before any work
    code, _, err = run(capsys, "eval", "--data", tmp_path / "nowhere")
    assert code == 2 and "nowhere: no such folder" in err
    code, _, err = run(capsys, "eval", "--data", root, "--backend", "nope")
    assert code == 2 and "unknown backend 'nope'; available: classical" in err


def test_eval_no_case_and_bad_split_exit_2(capsys, tmp_path: Path) -> None:  # noqa: ANN001
    root = tmp_path / "rig"
    write_blank_dataset(root, [translated_camera(f"v{i}", 0.25 * i, y) for i, y in enumerate((0, 5, 10))])
    code, _, err = run(capsys, "eval", "--data", root, "--split", "wide", "--out", tmp_path / "res")
    assert code == 2 and "no test case for split 'wide'" in err
    code, _, err = run(capsys, "eval", "--data", root, "--split", "huge")
    assert code == 2 and "unknown split 'huge'" in err and "generic layout" not in err  # before any work


def test_eval_partial_run_keeps_results_and_exits_2(capsys, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    root = write_plane_dataset(tmp_path / "p")
    png = root / "images" / "f5.png"
    ok, jpg = cv2.imencode(".jpg", cv2.imread(str(png)))
    png.unlink()
    data = jpg.tobytes()
    (root / "images" / "f5.jpg").write_bytes(data[: data.find(b"\xff\xda") + 20])  # header fine, no pixels
    out = tmp_path / "res"
    code, _, err = run(capsys, "eval", "--data", root, "--backend", "oracle", "--out", out, "--max-pairs", "0")
    assert code == 2
    assert "could not be evaluated because of bad input" in err and "f5.jpg" in err and str(out) in err
    doc = json.loads((out / "results.json").read_text())
    statuses = [c["status"] for c in doc["cases"]]
    assert "error" in statuses and "ok" in statuses and doc["complete"]
    assert all("f5.jpg: not an image OpenCV can decode" in e["error"] for e in doc["errors"])
    ok_cases = [c for c in doc["cases"] if c["status"] == "ok"]
    assert all(5 not in (*c["context"], *(t["index"] for t in c["targets"])) for c in ok_cases)


def test_bench_writes_markdown_plot_and_json(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    out = tmp_path / "bench"
    args = ["bench", "--data", plane, "--backend", "oracle", "--size", "64,96", "--split", "medium", "--out", out]
    code, stdout, err = run(capsys, *args, "--max-pairs", "1", "--json")
    assert code == 0, err
    doc = json.loads(stdout)
    assert [r["setting"]["size"] for r in doc["rows"]] == [64, 96] and any(r["pareto"] for r in doc["rows"])
    assert doc["metric"] == "psnr" and doc["higher_is_better"] is True
    md = (out / "bench.md").read_text()
    assert md.startswith("# macsplat bench:") and "Pareto front (time vs psnr" in md
    img = cv2.imread(str(out / "bench.png"))
    assert img is not None and img.shape == (560, 900, 3) and np.any(img != 255)
    assert json.loads((out / "bench.json").read_text())["rows"] == doc["rows"]
    code, _, err = run(capsys, *args, "--metric", "beauty")
    assert code == 2 and "--metric 'beauty'" in err


def test_eval_lpips_with_local_weights(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    """--lpips-weights adds LPIPS for every method (random weights in the official layouts here);
    a missing weights folder is bad input (exit 2) before any work."""
    import torch

    from macsplat_cli.lpips import LPIPS

    model = LPIPS()
    sd = {f"features.{i}.{p}": getattr(model.features[i], p).detach() for i in (0, 2, 5, 7, 10, 12, 14, 17, 19, 21,
          24, 26, 28) for p in ("weight", "bias")}  # fmt: skip
    torch.save(sd, tmp_path / "vgg16-397923af.pth")
    torch.save({f"lin{k}.model.1.weight": lin.weight.detach().abs() for k, lin in enumerate(model.lins)},
               tmp_path / "vgg.pth")  # fmt: skip
    args = ["eval", "--data", plane, "--backend", "oracle", "--split", "wide", "--json", "-q"]
    code, stdout, err = run(capsys, *args, "--out", tmp_path / "r", "--lpips-weights", tmp_path)
    assert code == 0, err
    summary = json.loads(stdout)["summary"]
    lp = {r["method"]: r["lpips"] for r in summary}
    assert set(lp) == {"oracle", "points", "copy"}
    assert all(v is not None and v >= 0 for v in lp.values())
    assert lp["oracle"] < lp["copy"]  # ground truth geometry looks more like the target than a context photo
    assert "lpips" in (tmp_path / "r" / "results.csv").read_text().splitlines()[0]
    code, _, err = run(capsys, *args, "--out", tmp_path / "s", "--lpips-weights", tmp_path / "nope")
    assert code == 2 and "nope" in err and not (tmp_path / "s").exists()
