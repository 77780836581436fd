"""``macsplat eval`` and ``macsplat bench`` with ``--context-views``, through the console-script entry point.

The ground-truth reconstructor is registered as a backend (as in ``test_cli_eval.py``); the data set is the
smooth plane of ``support.evaluation`` (six frames along a line).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from support.cli import run_captured

run = run_captured


def test_eval_with_three_context_views(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    out = tmp_path / "res"
    args = ["eval", "--data", plane, "--backend", "oracle", "--out", out, "--max-pairs", "1", "--json"]
    code, stdout, err = run(capsys, *args, "--context-views", "3")
    assert code == 0, err
    assert "3 context views each" in err and "reg./3" in err
    doc = json.loads((out / "results.json").read_text())
    assert doc["context_views"] == 3 and doc["options"]["context_views"] == 3 and doc["complete"]
    assert doc["cases"]
    for case in doc["cases"]:
        ctx = case["context"]
        assert len(ctx) == len(set(ctx)) == 3 and set(case["pair"]) < set(ctx)
        assert not set(ctx) & {t["index"] for t in case["targets"]}  # targets stay held out
        assert case["status"] == "ok" and case["registered"] == 3 and case["unregistered"] == []
        assert len(case["pairs"]) == 3 and case["rotation_error_deg"] < 1e-6
        assert all(t["metrics"]["oracle"]["psnr_masked"] >= 40.0 for t in case["targets"])
    rows = [r for r in json.loads(stdout)["summary"] if r["method"] == "oracle"]
    assert rows and all(r["context_views"] == 3 and r["registered"] == 3.0 for r in rows)
    header = (out / "results.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["scene", "split", "context_0", "context_1"] and "contexts" in header
    assert "registered / 3" in (out / "summary.md").read_text()


def test_bench_with_three_context_views(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    out = tmp_path / "bench"
    args = ["bench", "--data", plane, "--backend", "oracle", "--size", "64", "--split", "medium", "--out", out]
    code, stdout, err = run(capsys, *args, "--max-pairs", "1", "--context-views", "3", "--json")
    assert code == 0, err
    (row,) = json.loads(stdout)["rows"]
    assert row["summary"]["context_views"] == 3 and row["summary"]["failed"] == 0
    run_doc = json.loads((out / "runs" / "oracle_s64_td_r0_qbalanced" / "results.json").read_text())
    assert run_doc["context_views"] == 3 and all(len(c["context"]) == 3 for c in run_doc["cases"])
    md = (out / "bench.md").read_text()
    assert "3 context views each" in md and "registered / 3" in md


@pytest.mark.parametrize("command", ["eval", "bench"])
def test_bad_context_views_exit_2_before_any_work(capsys, plane: Path, tmp_path: Path, command: str) -> None:  # noqa: ANN001
    out = tmp_path / "res"
    for value, message in (("1", "give 2 to 64"), ("65", "give 2 to 64"), ("0", "give 2 to 64")):
        code, _, err = run(capsys, command, "--data", plane, "--out", out, "--context-views", value)
        assert code == 2 and f"--context-views {value}: {message}" in err, err
        assert len(err.strip().splitlines()) == 1 and not out.exists()
    code, _, err = run(capsys, command, "--data", plane, "--out", out, "--context-views", "3", "--backend", "neural")
    assert code == 2 and "the neural backend reconstructs two photos" in err and not out.exists()


def test_cases_without_enough_frames_are_left_out(capsys, plane: Path, tmp_path: Path) -> None:  # noqa: ANN001
    code, _, err = run(capsys, "eval", "--data", plane, "--out", tmp_path / "r", "--context-views", "6")
    assert code == 2 and "no test case can have 6 context views" in err and not (tmp_path / "r").exists()
