"""The library entry points of ``eval`` and ``bench`` (:mod:`macsplat_cli.evaluation.commands`): a spec in, the run
out, without typer; the same results as the commands', nothing drawn."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macsplat_cli import evaluation
from macsplat_cli._json import to_jsonable
from macsplat_cli.engine import EngineConfig
from macsplat_cli.errors import InputError
from macsplat_cli.presets import Overrides

from support.cli import run_captured

TIMES = ("time", "seconds")


def _untimed(rows: list[dict]) -> str:
    """The rows without their timings, as JSON text (NaN, for a metric not measured, equals itself there)."""
    return json.dumps([{k: v for k, v in r.items() if not any(t in k for t in TIMES)} for r in rows], sort_keys=True)


def test_run_gives_the_commands_results(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    options = ["--data", plane, "--backend", "oracle", "--split", "wide", "--max-pairs", "1", "--json", "-q"]
    code, stdout, err = run_captured(capsys, "eval", *options, "--out", tmp_path / "cli")
    assert code == 0, err
    spec = evaluation.EvalSpec(
        cases=evaluation.CaseSpec(plane, split="wide", max_pairs=1),
        engine=EngineConfig(backend="oracle"),  # type: ignore[arg-type]  # a backend the test registers
        out=tmp_path / "lib",
    )
    outcome = evaluation.run(spec)
    outcome.check()
    assert capsys.readouterr() == ("", "")  # the library draws nothing
    assert _untimed(to_jsonable(outcome.rows)) == _untimed(json.loads(stdout)["summary"])
    cli, lib = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("cli", "lib"))
    assert cli["options"] == lib["options"] and cli["cases_total"] == lib["cases_total"] == len(outcome.run.results)


def test_run_works_at_the_engines_size(plane: Path, tmp_path: Path, oracle_backend: None) -> None:
    """``--size`` has one owner, the engine's overrides (``reconstruct``'s): the views are compared at it."""
    for size in (64, 96):
        engine = EngineConfig(backend="oracle", overrides=Overrides(size=size))  # type: ignore[arg-type]
        spec = evaluation.EvalSpec(evaluation.CaseSpec(plane, split="wide", max_pairs=1), engine, tmp_path / f"{size}")
        outcome = evaluation.run(spec)
        outcome.check()
        sizes = [max(t.size) for r in outcome.run.results for t in r.targets]
        assert sizes and set(sizes) == {size}


def test_run_checks_everything_before_any_work(plane: Path, tmp_path: Path, oracle_backend: None) -> None:
    engine = EngineConfig(backend="oracle")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="--protocol mac-splat evaluates published test sets: give --cases"):
        evaluation.run(evaluation.EvalSpec(cases=evaluation.CaseSpec(plane, protocol="mac-splat"), engine=engine))
    with pytest.raises(InputError, match="is also the input --cases"):
        evaluation.run(
            evaluation.EvalSpec(
                cases=evaluation.CaseSpec(plane, cases_file=tmp_path / "o" / "results.json"), engine=engine,
                out=tmp_path / "o",
            )
        )  # fmt: skip
    assert not (tmp_path / "o").exists()


def test_benchmark_gives_the_commands_bench(capsys, plane: Path, tmp_path: Path, oracle_backend: None) -> None:  # noqa: ANN001
    options = ["--data", plane, "--backend", "oracle", "--size", "64,96", "--split", "wide", "--max-pairs", "1"]
    code, stdout, err = run_captured(capsys, "bench", *options, "--json", "-q", "--out", tmp_path / "cli")
    assert code == 0, err
    spec = evaluation.BenchSpec(
        cases=evaluation.CaseSpec(plane, split="wide", max_pairs=1, max_targets=2), out=tmp_path / "lib",
        backends=["oracle"], sizes=[64, 96],
    )  # fmt: skip
    rows = evaluation.benchmark(spec)
    assert capsys.readouterr() == ("", "")
    cli, lib = (json.loads((tmp_path / d / "bench.json").read_text()) for d in ("cli", "lib"))
    assert len(rows) == 2 and [r.setting.size for r in rows] == [r["setting"]["size"] for r in lib["rows"]]
    assert cli["rows"] and json.dumps(cli) == json.dumps(json.loads(stdout))  # the command prints what it wrote
    for a, b in zip(cli["rows"], lib["rows"], strict=True):
        assert a["setting"] == b["setting"]  # not "pareto": it weighs the measured seconds, which differ run to run
        assert _untimed([a["summary"]]) == _untimed([b["summary"]])
