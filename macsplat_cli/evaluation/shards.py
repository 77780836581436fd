"""Evaluation at scale: a run cut into shards (``eval --shard I/N``, a job array on any scheduler) and the shards'
results merged into the run one process would have written (``macsplat eval merge``).

A shard takes every N-th case of the full selection, starting at I (round robin: each shard gets a share of every
split and scene). Its ``results.json`` records the shard and the keys of *all* the run's cases, in order, so that
the merge can check that the shards belong together and cover the run, and put the cases back in their order.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .._atomic import atomic_write_text, check_folder
from ..errors import InputError
from .results import CaseResult, EvalConfig, EvalRun, TargetResult
from .splits import EvalCase

__all__ = ["MergeSummary", "case_from_dict", "merge_shards", "parse_shard", "result_from_dict", "shard_cases"]

_SHARD = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")
_VOLATILE = ("shard",)
"""Fields of ``results.json`` that differ between the shards of one run (besides the cases and the summary)."""


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` → ``(I, N)`` with ``0 ≤ I < N``; InputError otherwise."""
    m = _SHARD.match(text)
    if m is None or not int(m.group(1)) < int(m.group(2)):
        raise InputError(f"--shard {text!r}: give I/N with 0 <= I < N (e.g. 0/4 … 3/4)")
    return int(m.group(1)), int(m.group(2))


def shard_cases(cases: list[EvalCase], index: int, count: int) -> list[EvalCase]:
    """The cases of shard ``index`` of ``count``: every ``count``-th, from ``index``."""
    return cases[index::count]


def shard_record(cases: list[EvalCase], index: int, count: int) -> dict[str, Any]:
    """What a shard's ``results.json`` says of its place in the run."""
    return {"index": index, "count": count, "cases_total": len(cases), "case_keys": [c.key for c in cases]}


def case_from_dict(d: dict[str, Any]) -> EvalCase:
    """The inverse of :meth:`EvalCase.to_dict`."""
    overlap = d.get("overlap")
    return EvalCase(
        scene=d["scene"], split=d["split"], context=tuple(d["context"]), targets=tuple(d["targets"]),
        criterion=d.get("criterion", "file"), overlap=math.nan if overlap is None else float(overlap),
        pair=tuple(d["pair"]) if d.get("pair") is not None else None,  # type: ignore[arg-type]
    )  # fmt: skip


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def result_from_dict(d: dict[str, Any]) -> CaseResult:
    """The inverse of :meth:`CaseResult.to_dict` (NaNs were written as null)."""
    return CaseResult(
        case=case_from_dict(d), method=d["method"], status=d["status"], error=d.get("error"),
        time_s=_num(d.get("time_s")), rotation_error_deg=_num(d.get("rotation_error_deg")),
        translation_error_deg=_num(d.get("translation_error_deg")),
        focal_error_pct=list(d.get("focal_error_pct") or [None, None]), depth=dict(d.get("depth") or {}),
        scale=_num(d.get("scale")),
        targets=[TargetResult(t["index"], t["name"], tuple(t["size"]), t["metrics"]) for t in d.get("targets", [])],  # type: ignore[arg-type]
        registered=d.get("registered_contexts"), unregistered=list(d.get("unregistered") or []),
        pairs=list(d.get("pairs") or []),
    )  # fmt: skip


@dataclass(frozen=True)
class MergeSummary:
    run: EvalRun
    shards: int
    cases: int


def _read(folder: Path) -> dict[str, Any]:
    path = folder / "results.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{folder}: no results.json (not an eval --out folder)") from None
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot be read: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("shard"), dict):
        raise InputError(f"{path}: not a shard's results (run eval with --shard I/N)")
    return doc


def _same_run(docs: list[tuple[Path, dict[str, Any]]]) -> None:
    def identity(doc: dict[str, Any]) -> dict[str, Any]:
        keep = {k: v for k, v in doc.items() if k not in (*_VOLATILE, "cases", "summary", "complete", "cases_done",
                                                           "pending", "errors", "cases_total")}  # fmt: skip
        return {**keep, "run_cases": doc["shard"]["case_keys"], "count": doc["shard"]["count"]}

    first_path, first = docs[0][0], identity(docs[0][1])
    for path, doc in docs[1:]:
        other = identity(doc)
        if other != first:
            diff = sorted(k for k in first.keys() | other.keys() if first.get(k) != other.get(k))
            raise InputError(f"{path} and {first_path} are shards of different runs (they differ in {', '.join(diff)})")


def merge_shards(folders: list[Path], out: Path) -> MergeSummary:
    """Check that ``folders`` are the complete shards of one run, then write the merged run into ``out`` (the
    files of :class:`~.result_files.ResultWriter`, and the first shard's ``coverage/``).

    Raises:
        InputError: a folder that is not a shard, shards of different runs, a missing, repeated or unfinished shard.
    """
    from .result_files import ResultWriter

    docs = [(f, _read(f)) for f in folders]
    _same_run(docs)
    count = docs[0][1]["shard"]["count"]
    seen: dict[int, Path] = {}
    for path, doc in docs:
        i = doc["shard"]["index"]
        if i in seen:
            raise InputError(f"shard {i}/{count} given twice: {seen[i]} and {path}")
        if not doc.get("complete"):
            raise InputError(f"{path}: shard {i}/{count} did not finish ({doc.get('cases_done')} of "
                             f"{doc.get('cases_total')} cases): run it again")  # fmt: skip
        seen[i] = path
    missing = [f"{i}/{count}" for i in range(count) if i not in seen]
    if missing:
        raise InputError(f"shard(s) {', '.join(missing)} missing: merge needs all {count}")
    first = docs[0][1]
    by_key = {case_from_dict(c).key: c for _, doc in docs for c in doc["cases"]}
    keys = first["shard"]["case_keys"]
    cases = [case_from_dict(by_key[k]) for k in keys]
    results = [result_from_dict(by_key[k]) for k in keys]
    config = EvalConfig(baselines=tuple(first["config"].get("baselines", ())))
    run = EvalRun(first["dataset"], first["layout"], first["method"], config, cases, results)
    extra = {k: v for k, v in first.items() if k not in {"dataset", "layout", "method", "context_views", "config",
             "complete", "cases_total", "cases_done", "pending", "errors", "summary", "cases", *_VOLATILE}}  # fmt: skip
    extra["merged_from"] = [str(f) for f in folders]
    writer = ResultWriter(out, extra, config_json=first["config"])
    writer.write(run)
    coverage = docs[0][0] / "coverage"
    for f in sorted(coverage.glob("*.json")) if coverage.is_dir() else []:
        atomic_write_text(check_folder(out / "coverage") / f.name, f.read_text(encoding="utf-8"))
    return MergeSummary(run, count, len(results))
