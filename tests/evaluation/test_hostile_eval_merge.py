"""Hostile shards given to ``eval merge`` (issue 37, E1–E4 and C2): every case is one line on stderr and exit 2,
naming the file, and nothing is written into ``--out``.

* E1 a malformed shard ``results.json`` (a missing or mistyped field, cases that are not the shard's) names the file
  and the field (it used to crash with KeyError);
* E2 a link anywhere in a shard (``coverage/*.json``, ``coverage/``, ``results.json``) is refused, never followed;
* E3 a FIFO as ``results.json`` or in ``coverage/`` is refused without blocking, a file over the size cap is refused,
  and a failed write leaves no output at all (the merge writes all or nothing);
* E4 ``--shard I/N`` and a shard's ``count`` are bounded (:data:`MAX_SHARDS`), and a merge missing many shards
  names a few of them in a short line;
* C2 an ``--out`` inside an input shard is refused.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import macsplat_cli.evaluation.shards as shards
from macsplat_cli.errors import InputError
from macsplat_cli.evaluation.shards import MAX_SHARDS, parse_shard

from support.cli import file_size_limit, one_error_line, run_captured


@pytest.fixture(scope="module")
def two_shards(plane: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with ``s0`` and ``s1``: the two shards of an oracle-backend run on the plane (read only: copy them)."""
    from macsplat_cli.cli import main
    from macsplat_cli.evaluation.reconstructors import BACKENDS

    from support.evaluation import ORACLE

    root = tmp_path_factory.mktemp("two_shards")
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(BACKENDS, "oracle", lambda config, models=None: ORACLE)
        for i in range(2):
            args = ["eval", "--data", plane, "--backend", "oracle", "-q", "--shard", f"{i}/2", "--out", root / f"s{i}"]
            assert main([str(a) for a in args]) == 0
    assert (root / "s0" / "coverage" / "plane.json").is_file()
    return root


@pytest.fixture
def shard_copies(two_shards: Path, tmp_path: Path) -> tuple[Path, Path]:
    """Writable copies of the two shards."""
    for name in ("s0", "s1"):
        shutil.copytree(two_shards / name, tmp_path / name)
    return tmp_path / "s0", tmp_path / "s1"


@contextlib.contextmanager
def _deadline(seconds: int) -> Iterator[None]:
    """A TimeoutError in this thread after ``seconds`` (a blocked open() of a FIFO is interrupted too)."""

    def expire(signum: int, frame: Any) -> None:
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _merge(capsys: pytest.CaptureFixture[str], *folders: Path, out: Path) -> tuple[int, str]:
    with _deadline(20):
        code, _, err = run_captured(capsys, "eval", "merge", *folders, "--out", out)
    return code, err


def _edit(shard: Path, change: Callable[[dict[str, Any]], None]) -> None:
    path = shard / "results.json"
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def test_the_shards_merge(capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path) -> None:
    """The inputs of the tests below are good: what they change is what is refused."""
    code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    assert code == 0, err
    assert (tmp_path / "m" / "coverage" / "plane.json").read_bytes() == (
        shard_copies[0] / "coverage" / "plane.json"
    ).read_bytes()


# ------------------------------------------------------------------------------------------------ E1
def _first_case(doc: dict[str, Any]) -> dict[str, Any]:
    return doc["cases"][0]


MALFORMED: dict[str, tuple[Callable[[dict[str, Any]], None], str]] = {
    "empty shard record": (lambda d: d.__setitem__("shard", {}), "shard.index is missing"),
    "no case_keys": (lambda d: d["shard"].pop("case_keys"), "shard.case_keys is missing"),
    "count a string": (lambda d: d["shard"].__setitem__("count", "2"), "shard.count is not an integer"),
    "case_keys too short": (lambda d: d["shard"]["case_keys"].pop(), "shard.case_keys is not the run's"),
    "bogus case": (lambda d: d.__setitem__("cases", [{"x": 1}]), "cases[0].scene is missing"),
    "no cases": (lambda d: d.__setitem__("cases", []), "its cases are not shard 0/2's share"),
    "cases not a list": (lambda d: d.__setitem__("cases", {"a": 1}), "field cases is not a list"),
    "a case of another shard": (
        lambda d: _first_case(d).__setitem__("context", [9, 8]),
        "its cases are not shard 0/2's share",
    ),
    "a string metric": (
        lambda d: next(iter(_first_case(d)["targets"][0]["metrics"].values())).__setitem__("psnr", "high"),
        "cases[0].targets is not a list of target results",
    ),
    "an unknown status": (lambda d: _first_case(d).__setitem__("status", "great"), "cases[0].status"),
    "a string time": (lambda d: _first_case(d).__setitem__("time_s", "fast"), "cases[0].time_s is not a number"),
    "config a list": (lambda d: d.__setitem__("config", []), "field config is not an object"),
}


@pytest.mark.parametrize("variant", list(MALFORMED))
def test_a_malformed_shard_document_is_refused_naming_the_file_and_field(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path, variant: str
) -> None:
    change, message = MALFORMED[variant]
    _edit(shard_copies[0], change)
    code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    line = one_error_line(err)
    assert code == 2 and str(shard_copies[0] / "results.json") in line and message in line, line
    assert not (tmp_path / "m").exists()


# ------------------------------------------------------------------------------------------------ E2
def _link_in_coverage(s0: Path, outside: Path) -> Path:
    (s0 / "coverage" / "leak.json").symlink_to(outside)
    return s0 / "coverage" / "leak.json"


def _coverage_a_link(s0: Path, outside: Path) -> Path:
    shutil.copytree(s0 / "coverage", outside.parent / "cov")
    shutil.rmtree(s0 / "coverage")
    (s0 / "coverage").symlink_to(outside.parent / "cov")
    return s0 / "coverage"


def _results_a_link(s0: Path, outside: Path) -> Path:
    (s0 / "results.json").rename(outside.parent / "results.json")
    (s0 / "results.json").symlink_to(outside.parent / "results.json")
    return s0 / "results.json"


@pytest.mark.parametrize("plant", [_link_in_coverage, _coverage_a_link, _results_a_link])
def test_a_link_in_a_shard_is_refused_not_followed(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path,
    plant: Callable[[Path, Path], Path],
) -> None:  # fmt: skip
    (tmp_path / "outside").mkdir()
    secret = tmp_path / "outside" / "secret.json"
    secret.write_text('{"secret": "OUTSIDE-SECRET"}\n')
    link = plant(shard_copies[0], secret)
    code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    line = one_error_line(err)
    assert code == 2 and str(link) in line and "symbolic link" in line, line
    assert not (tmp_path / "m").exists()


# ------------------------------------------------------------------------------------------------ E3
def test_a_fifo_as_results_json_is_refused_without_blocking(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path
) -> None:
    (shard_copies[0] / "results.json").unlink()
    os.mkfifo(shard_copies[0] / "results.json")
    code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    assert code == 2 and "not a regular file" in one_error_line(err), err
    assert not (tmp_path / "m").exists()


def test_a_fifo_in_coverage_is_refused_before_anything_is_written(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path
) -> None:
    os.mkfifo(shard_copies[0] / "coverage" / "zz.json")
    code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    assert code == 2 and "zz.json: not a regular file" in one_error_line(err), err
    assert not (tmp_path / "m").exists()  # no half-merged output


def test_a_shard_file_over_the_size_cap_is_refused(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    size = (shard_copies[0] / "results.json").stat().st_size
    monkeypatch.setattr(shards, "MAX_SHARD_FILE_BYTES", size - 1)
    code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    assert code == 2 and "too large" in one_error_line(err), err


def test_a_failed_write_leaves_no_merged_file(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path
) -> None:
    """A write that fails after the first file (results.json is larger than cases.jsonl, written first) leaves none
    of the merge's files: all or nothing."""
    assert _merge(capsys, *shard_copies, out=tmp_path / "good")[0] == 0
    small, large = ((tmp_path / "good" / n).stat().st_size for n in ("cases.jsonl", "results.json"))
    assert small < large
    with file_size_limit((small + large) // 2):
        code, err = _merge(capsys, *shard_copies, out=tmp_path / "m")
    assert code == 2 and "cannot write" in one_error_line(err), err
    assert sorted(p.name for p in (tmp_path / "m").rglob("*")) in ([], ["coverage"]), list((tmp_path / "m").rglob("*"))


# ------------------------------------------------------------------------------------------------ E4
def test_the_shard_count_is_bounded_before_any_work(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert parse_shard(f"{MAX_SHARDS - 1}/{MAX_SHARDS}") == (MAX_SHARDS - 1, MAX_SHARDS)
    for bad in (f"0/{MAX_SHARDS + 1}", "0/1000000000000", "0/" + "9" * 5000, "9" * 5000 + "/4"):
        with pytest.raises(InputError, match="--shard") as e:
            parse_shard(bad)
        assert len(str(e.value)) < 200
    code, _, err = run_captured(capsys, "eval", "--data", tmp_path / "no-data", "--shard", "0/1000000000000",
                                "--out", tmp_path / "out")  # fmt: skip
    assert code == 2 and "at most 10,000 shards" in one_error_line(err), err
    assert not (tmp_path / "out").exists()


def test_a_forged_shard_count_gives_a_short_error(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path], tmp_path: Path
) -> None:
    """A count over the bound is refused; one within it, with most shards missing, names ten of them."""
    _edit(shard_copies[0], lambda d: d["shard"].__setitem__("count", 10 * MAX_SHARDS))
    code, err = _merge(capsys, shard_copies[0], out=tmp_path / "m")
    assert code == 2 and f"shard 0/{10 * MAX_SHARDS} is not I/N" in one_error_line(err) and len(err) < 2000, err
    _edit(shard_copies[0], lambda d: d["shard"].__setitem__("count", MAX_SHARDS))
    code, err = _merge(capsys, shard_copies[0], out=tmp_path / "m")
    line = one_error_line(err)
    assert code == 2 and f"and {MAX_SHARDS - 11:,} more missing" in line and len(err) < 2000, err


# ------------------------------------------------------------------------------------------------ C2
def test_out_inside_an_input_shard_is_refused(
    capsys: pytest.CaptureFixture[str], shard_copies: tuple[Path, Path]
) -> None:
    s0, s1 = shard_copies
    for out in (s0 / "coverage", s1 / "deeper" / "m"):
        code, err = _merge(capsys, s0, s1, out=out)
        assert code == 2 and "inside the shard" in one_error_line(err), err
    assert not (s0 / "coverage" / "results.json").exists() and not (s1 / "deeper").exists()
