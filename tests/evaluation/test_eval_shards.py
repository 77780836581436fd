"""eval --shard I/N and eval merge: the shards of a run, merged, are the run one process writes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macsplat_cli.errors import InputError
from macsplat_cli.evaluation.shards import parse_shard, result_from_dict, shard_cases

from support.cli import run_captured


def _timeless(obj):  # noqa: ANN001, ANN202 - JSON
    """The document without wall times (they differ between any two runs)."""
    if isinstance(obj, dict):
        return {k: _timeless(v) for k, v in obj.items() if not k.startswith("time")}
    if isinstance(obj, list):
        return [_timeless(v) for v in obj]
    return obj


def test_parse_shard_and_round_robin() -> None:
    assert parse_shard("0/4") == (0, 4) and parse_shard(" 3 / 4 ") == (3, 4)
    for bad in ("4/4", "-1/2", "1", "a/b", "1/0"):
        with pytest.raises(InputError, match="--shard"):
            parse_shard(bad)
    items = list(range(10))
    parts = [shard_cases(items, i, 3) for i in range(3)]  # type: ignore[arg-type]
    assert parts == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]] and sorted(sum(parts, [])) == items


def test_merged_shards_equal_one_process(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    common = ["eval", "--data", plane, "--backend", "oracle", "-q"]
    assert run_captured(capsys, *common, "--out", tmp_path / "one")[0] == 0
    for i in range(3):
        assert run_captured(capsys, *common, "--shard", f"{i}/3", "--out", tmp_path / f"s{i}")[0] == 0
    shard0 = json.loads((tmp_path / "s0" / "results.json").read_text())
    one = json.loads((tmp_path / "one" / "results.json").read_text())
    assert 0 < shard0["cases_total"] < one["cases_total"] == shard0["shard"]["cases_total"]
    code, _, err = run_captured(capsys, "eval", "merge", *(tmp_path / f"s{i}" for i in (2, 0, 1)), "--out",
                                tmp_path / "merged")  # fmt: skip
    assert code == 0, err
    merged = json.loads((tmp_path / "merged" / "results.json").read_text())
    assert merged.pop("merged_from")
    assert _timeless(merged) == _timeless(one)
    lines = [(tmp_path / f / "cases.jsonl").read_text() for f in ("merged", "one")]
    assert _timeless_lines(lines[0]) == _timeless_lines(lines[1])
    csvs = [(tmp_path / f / "results.csv").read_text().splitlines() for f in ("merged", "one")]
    assert len(csvs[0]) == len(csvs[1]) and csvs[0][0] == csvs[1][0]  # the same rows (their times differ)
    assert (tmp_path / "merged" / "coverage" / "plane.json").read_text() == (
        tmp_path / "one" / "coverage" / "plane.json"
    ).read_text()
    again = result_from_dict(one["cases"][0])
    assert again.to_dict() == one["cases"][0]  # the results read back exactly


def _timeless_lines(text: str) -> list:
    return [_timeless(json.loads(line)) for line in text.splitlines()]


def test_merge_refuses_missing_repeated_or_foreign_shards(
    capsys, plane: Path, tmp_path: Path, oracle_backend: None
) -> None:  # noqa: ANN001, E501
    common = ["eval", "--data", plane, "--backend", "oracle", "-q"]
    for i in range(2):
        assert run_captured(capsys, *common, "--shard", f"{i}/2", "--out", tmp_path / f"s{i}")[0] == 0
    assert run_captured(capsys, *common, "--shard", "0/2", "--seed", "5", "--out", tmp_path / "other")[0] == 0
    assert run_captured(capsys, *common, "--out", tmp_path / "plain")[0] == 0
    cases = {
        "missing": ([tmp_path / "s0"], "shard(s) 1/2 missing: merge needs all 2"),
        "twice": ([tmp_path / "s0", tmp_path / "s0", tmp_path / "s1"], "shard 0/2 given twice"),
        "foreign": ([tmp_path / "s0", tmp_path / "other"], "shards of different runs"),
        "not a shard": ([tmp_path / "plain"], "not a shard's results"),
        "no results": ([tmp_path], "no results.json"),
    }
    for why, (folders, message) in cases.items():
        code, _, err = run_captured(capsys, "eval", "merge", *folders, "--out", tmp_path / "m")
        assert code == 2 and message in err, (why, err)


def _close(a, b, path: str = "") -> list[str]:  # noqa: ANN001 - JSON
    """Where two JSON documents differ beyond float rounding (torch reductions round differently with other thread
    counts); their paths."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for k in a for d in _close(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} != {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _close(x, y, f"{path}/{i}")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if abs(a - b) <= 1e-6 * max(1.0, abs(a), abs(b)) else [f"{path}: {a} != {b}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def test_jobs_runs_the_shards_as_processes_and_merges_them(capsys, plane: Path, tmp_path: Path) -> None:  # noqa: ANN001
    """--jobs 2 (two real processes, the classical backend) writes what one process writes."""
    common = ["eval", "--data", plane, "--split", "close,medium", "--max-pairs", "1", "--max-targets", "1",
              "--no-baselines", "--size", "128", "-q"]  # fmt: skip
    code, _, err = run_captured(capsys, *common, "--out", tmp_path / "one")
    assert code == 0, err
    code, _, err = run_captured(capsys, *common, "--jobs", "2", "--out", tmp_path / "jobs")
    assert code == 0, err
    one = json.loads((tmp_path / "one" / "results.json").read_text())
    jobs = json.loads((tmp_path / "jobs" / "results.json").read_text())
    assert len(jobs.pop("merged_from")) == 2 and one["cases_total"] >= 2
    assert _close(_timeless(jobs), _timeless(one)) == []
    code, _, err = run_captured(capsys, *common, "--jobs", "2", "--shard", "0/2", "--out", tmp_path / "x")
    assert code == 2 and "--jobs and --shard" in err
