"""``macsplat bench --matcher sift,auto,aliked`` sweeps the matcher as the other grid axes: one setting per matcher,
each run with its matcher, the table and JSON naming it; an unknown matcher is a usage error before any work."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macsplat_cli.evaluation.bench import BenchSetting, grid
from macsplat_cli.presets import DEFAULT_MATCHER

from support.cli import run_captured


def test_grid_sweeps_the_matcher_of_the_classical_backend_only() -> None:
    g = grid(["classical", "neural"], [256], matchers=["sift", "auto"])
    assert g == [BenchSetting("classical", 256, matcher="sift"), BenchSetting("classical", 256, matcher="auto"),
                 BenchSetting("neural", 256, matcher=DEFAULT_MATCHER)]  # fmt: skip
    by = {s.matcher: s for s in g[:2]}  # the default is named by neither slug nor label, the other by both
    other = next(m for m in by if m != DEFAULT_MATCHER)
    assert by[other].slug.endswith(f"_m{other}") and by[DEFAULT_MATCHER].slug == "classical_s256_td_r0_qbalanced"
    assert by[other].label.endswith(f"matcher={other}") and "matcher" not in by[DEFAULT_MATCHER].label


def test_bench_runs_each_setting_with_its_matcher(capsys, plane: Path, tmp_path: Path,  # noqa: ANN001
                                                  monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    from macsplat_cli.evaluation.reconstructors import BACKENDS

    from support.evaluation import ORACLE

    seen: list[str] = []

    def factory(config, models=None):  # noqa: ANN001, ANN202
        seen.append(config.matcher)
        return ORACLE

    monkeypatch.setitem(BACKENDS, "oracle", factory)
    out = tmp_path / "bench"
    args = ["bench", "--data", plane, "--backend", "oracle", "--size", "64", "--split", "medium", "--max-pairs", "1"]
    code, stdout, err = run_captured(capsys, *args, "--matcher", "sift, AUTO,aliked", "--out", out, "--json")
    assert code == 0, err
    assert seen == ["sift", "auto", "aliked"]
    rows = json.loads(stdout)["rows"]
    assert [r["setting"]["matcher"] for r in rows] == ["sift", "auto", "aliked"]
    md = (out / "bench.md").read_text()
    assert "| quality | matcher |" in md and all(f"| {m} |" in md.replace("**", "") for m in ("sift", "auto", "aliked"))
    assert (out / "runs" / "oracle_s64_td_r0_qbalanced_maliked" / "results.json").is_file()
    code, _, err = run_captured(capsys, *args, "--matcher", "sift,orb", "--out", tmp_path / "b2")
    assert code == 2 and "--matcher" in err and "orb" in err and not (tmp_path / "b2").exists()
