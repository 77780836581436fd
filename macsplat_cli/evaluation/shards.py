"""Evaluation at scale: a run cut into shards (``eval --shard I/N``, a job array on any scheduler) and the shards'
results merged into the run one process would have written (``macsplat eval merge``).

A shard takes every N-th case of the full selection, starting at I (round robin: each shard gets a share of every
split and scene). Its ``results.json`` records the shard and the keys of *all* the run's cases, in order, so that
the merge can check that the shards belong together and cover the run, and put the cases back in their order.

**What a merge reads.** Only each shard's ``results.json`` and the first shard's ``coverage/*.json``: regular files
inside the shard folder (links resolved; a link, FIFO or device at such a name is refused: opened without following
a link and without blocking), of at most :data:`MAX_SHARD_FILE_BYTES`, parsed with the nesting cap of every JSON
input. Each document is checked field by field (a missing or mistyped field is one error naming the file and the
field), and everything is read and checked before the first output is written; the outputs are then written all or
nothing (each to a temporary file beside it, the temporaries renamed once all are written).
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .._atomic import atomic_path, check_folder
from .._limits import MAX_TEXT_BYTES, parse_json
from ..errors import InputError
from .results import CaseResult, EvalConfig, EvalRun, TargetResult
from .splits import EvalCase

__all__ = [
    "MAX_SHARDS",
    "MAX_SHARD_FILE_BYTES",
    "MergeSummary",
    "case_from_dict",
    "merge_shards",
    "parse_shard",
    "result_from_dict",
    "shard_cases",
]

_SHARD = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")
_VOLATILE = ("shard",)
"""Fields of ``results.json`` that differ between the shards of one run (besides the cases and the summary)."""
MAX_SHARDS = 10_000
"""The most shards one run is cut into (``--shard I/N``): far more jobs than any test set has cases, and a bound on
what a merge allocates for a forged shard (it lists the N shards it needs)."""
MAX_SHARD_FILE_BYTES = MAX_TEXT_BYTES
"""A shard's ``results.json`` or coverage file larger than this is refused (256 MiB: a case takes about 2 kB, the
coverage matrix of a 2,000-frame scene about 40 MB)."""
_NAMED_MISSING = 10
"""Missing shards named in the merge's error line; the rest are counted."""


def _cut(text: str, at: int = 40) -> str:
    """``text`` for an error line: at most ``at`` characters."""
    return text if len(text) <= at else text[:at] + "…"


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` → ``(I, N)`` with ``0 ≤ I < N ≤`` :data:`MAX_SHARDS`; InputError otherwise (before any work)."""
    m = _SHARD.match(text)
    index, count = (g.lstrip("0") or "0" for g in m.groups()) if m is not None else ("1", "0")
    if len(count) > len(str(MAX_SHARDS)) or int(count) > MAX_SHARDS:  # lengths first: int() of 5,000 digits raises
        raise InputError(f"--shard {_cut(text)!r}: at most {MAX_SHARDS:,} shards (N)")
    if len(index) > len(count) or not int(index) < int(count):
        raise InputError(f"--shard {_cut(text)!r}: give I/N with 0 <= I < N (e.g. 0/4 … 3/4)")
    return int(index), int(count)


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
        pair=tuple(d["pair"]) if d.get("pair") is not None else None,
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
        targets=[TargetResult(t["index"], t["name"], tuple(t["size"]), t["metrics"]) for t in d.get("targets", [])],
        registered=d.get("registered_contexts"), unregistered=list(d.get("unregistered") or []),
        pairs=list(d.get("pairs") or []),
    )  # fmt: skip


@dataclass(frozen=True)
class MergeSummary:
    """What a merge wrote: the merged run, its number of shards and of cases."""

    run: EvalRun
    shards: int
    cases: int


# ------------------------------------------------------------------------------------------------ reading a shard
def _read_file(path: Path, shard: Path) -> str:
    """The UTF-8 text of ``path``, a regular file of at most :data:`MAX_SHARD_FILE_BYTES` inside the folder ``shard``.

    Raises:
        FileNotFoundError: nothing at ``path``.
        InputError: ``path`` is a link, a folder, a FIFO, a device or a socket, lies (its folder's links resolved)
            outside ``shard``, is too large, or is not UTF-8.
    """
    root = os.path.realpath(shard)
    if os.path.commonpath([root, os.path.realpath(path.parent)]) != root:
        raise InputError(f"{path}: outside its shard {shard} (a link leads out of it); eval merge reads only the "
                         "shards' own files")  # fmt: skip
    st = os.lstat(path)  # FileNotFoundError for the caller
    if stat.S_ISLNK(st.st_mode):
        raise InputError(f"{path}: a symbolic link; eval merge reads only the shards' own files, never a link")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path}: not a regular file (a folder, device, FIFO or socket cannot be shard results)")
    try:  # no link followed, no wait on a FIFO swapped in since the lstat
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        why = "a symbolic link" if e.errno == errno.ELOOP else e.strerror
        raise InputError(f"{path}: cannot be read: {why}") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise InputError(f"{path}: not a regular file (a device, FIFO or socket cannot be shard results)")
        data = f.read(MAX_SHARD_FILE_BYTES + 1)
    if len(data) > MAX_SHARD_FILE_BYTES:
        raise InputError(f"{path}: too large for shard results (at most {MAX_SHARD_FILE_BYTES:,} bytes)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def _read(folder: Path) -> dict[str, Any]:
    """A shard's ``results.json``, read (:func:`_read_file`) and parsed; its ``shard`` record checked."""
    path = folder / "results.json"
    try:
        text = _read_file(path, folder)
    except (FileNotFoundError, NotADirectoryError):
        raise InputError(f"{folder}: no results.json (not an eval --out folder)") from None
    except OSError as e:
        raise InputError(f"{path}: cannot be read: {e.strerror or e}") from None
    doc = parse_json(text, str(path), InputError)
    if not isinstance(doc, dict) or not isinstance(doc.get("shard"), dict):
        raise InputError(f"{path}: not a shard's results (run eval with --shard I/N)")
    for name, kind, what in (("dataset", str, "a name"), ("layout", str, "a name"), ("method", str, "a name"),
                             ("config", dict, "an object"), ("cases", list, "a list")):  # fmt: skip
        _check(path, doc, name, _of_type(kind), what)
    _check(path, doc["config"], "baselines", _strs, "a list of names", "config.", required=False)
    shard = doc["shard"]
    for name in ("index", "count", "cases_total"):
        _check(path, shard, name, _int, "an integer", "shard.")
    _check(path, shard, "case_keys", _strs, "a list of case keys", "shard.")
    index, count, keys = shard["index"], shard["count"], shard["case_keys"]
    if not (1 <= count <= MAX_SHARDS and 0 <= index < count):
        raise InputError(f"{path}: shard {index}/{count} is not I/N with 0 <= I < N <= {MAX_SHARDS:,}")
    if len(keys) != shard["cases_total"] or len(set(keys)) != len(keys):
        raise InputError(f"{path}: shard.case_keys is not the run's {shard['cases_total']} distinct case keys")
    return doc


def _read_coverage(folder: Path) -> dict[str, str]:
    """A shard's ``coverage/*.json`` (hidden files skipped: temporaries), each read (:func:`_read_file`) and
    parsed: name → text."""
    coverage = folder / "coverage"
    try:
        st = os.lstat(coverage)
    except (FileNotFoundError, NotADirectoryError):
        return {}
    if not stat.S_ISDIR(st.st_mode):
        kind = "a symbolic link" if stat.S_ISLNK(st.st_mode) else "not a folder"
        raise InputError(f"{coverage}: {kind}; eval merge reads only the shards' own files")
    texts = {}
    try:
        names = sorted(e.name for e in os.scandir(coverage))
    except OSError as e:
        raise InputError(f"{coverage}: cannot be read: {e.strerror or e}") from None
    for name in names:
        if name.endswith(".json") and not name.startswith("."):
            try:
                texts[name] = _read_file(coverage / name, folder)
            except OSError as e:
                raise InputError(f"{coverage / name}: cannot be read: {e.strerror or e}") from None
            parse_json(texts[name], str(coverage / name), InputError)
    return texts


# ------------------------------------------------------------------------------------------------ checking a shard
def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v: Any) -> bool:
    """A number, or null (a NaN as JSON writes it)."""
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))


def _strs(v: Any) -> bool:
    return isinstance(v, list) and all(isinstance(x, str) for x in v)


def _ints(v: Any) -> bool:
    return isinstance(v, list) and all(_int(x) for x in v)


def _numbers(v: Any) -> bool:
    """``{name: number or null}``."""
    return isinstance(v, dict) and all(_number(x) for x in v.values())


def _target(v: Any) -> bool:
    """One target's entry: ``{index, name, size: [w, h], metrics: {method: {metric: number}}}``."""
    return (isinstance(v, dict) and _int(v.get("index")) and isinstance(v.get("name"), str)
            and _ints(v.get("size")) and len(v["size"]) == 2 and isinstance(v.get("metrics"), dict)
            and all(_numbers(m) for m in v["metrics"].values()))  # fmt: skip


def _optional(check: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda v: v is None or check(v)


_CASE_FIELDS: dict[str, tuple[bool, Callable[[Any], bool], str]] = {
    "scene": (True, lambda v: isinstance(v, str), "a name"),
    "split": (True, lambda v: isinstance(v, str), "a name"),
    "context": (True, lambda v: _ints(v) and len(v) >= 2, "a list of at least two frame numbers"),
    "targets": (True, lambda v: isinstance(v, list) and all(_target(t) for t in v), "a list of target results"),
    "method": (True, lambda v: isinstance(v, str), "a name"),
    "status": (True, lambda v: v in ("ok", "failed", "error"), "ok, failed or error"),
    "error": (False, _optional(lambda v: isinstance(v, str)), "a message"),
    "criterion": (False, lambda v: isinstance(v, str), "a name"),
    "pair": (False, _optional(lambda v: _ints(v) and len(v) == 2), "two frame numbers"),
    "focal_error_pct": (False, _optional(lambda v: isinstance(v, list) and all(map(_number, v))), "a list of numbers"),
    "depth": (False, _optional(_numbers), "numbers by name"),
    "registered_contexts": (False, _optional(_ints), "a list of frame numbers"),
    "unregistered": (False, _optional(lambda v: isinstance(v, list)), "a list"),
    "pairs": (False, _optional(lambda v: isinstance(v, list)), "a list"),
    **{k: (False, _number, "a number") for k in ("overlap", "time_s", "rotation_error_deg", "translation_error_deg",
                                                  "scale")},
}  # fmt: skip
"""What :func:`result_from_dict` and the summary need of a case: (required, check, what it must be)."""


def _of_type(kind: type) -> Callable[[Any], bool]:
    """The check that a value is a ``kind``."""
    return lambda v: isinstance(v, kind)


def _check(
    path: Path, obj: dict[str, Any], name: str, ok: Callable[[Any], bool], what: str, where: str = "",
    required: bool = True,
) -> None:  # fmt: skip
    """InputError naming the file and the field unless ``obj[name]`` passes ``ok`` (or is absent and optional)."""
    if name not in obj:
        if required:
            raise InputError(f"{path}: field {where}{name} is missing (not a shard's complete results.json)")
    elif not ok(obj[name]):
        raise InputError(f"{path}: field {where}{name} is not {what} ({_cut(repr(obj[name]))})")


def _results(path: Path, doc: dict[str, Any]) -> list[CaseResult]:
    """A complete shard's case results, each checked, and checked to be exactly its share of the run's cases."""
    results = []
    for i, d in enumerate(doc["cases"]):
        if not isinstance(d, dict):
            raise InputError(f"{path}: cases[{i}] is not an object")
        for name, (required, ok, what) in _CASE_FIELDS.items():
            _check(path, d, name, ok, what, f"cases[{i}].", required)
        results.append(result_from_dict(d))
    shard = doc["shard"]
    want = shard["case_keys"][shard["index"] :: shard["count"]]
    got = [r.case.key for r in results]
    if got != want:
        first = next(
            (f"{g!r} where {w!r} belongs" for g, w in zip(got, want) if g != w),
            f"it has {len(got)} of its {len(want)} cases",
        )
        raise InputError(f"{path}: its cases are not shard {shard['index']}/{shard['count']}'s share of the run "
                         f"({_cut(first, 120)})")  # fmt: skip
    return results


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


def _check_complete(docs: list[tuple[Path, dict[str, Any]]]) -> int:
    """The run's shard count N, once every shard 0 … N−1 is given once and finished."""
    count = docs[0][1]["shard"]["count"]
    seen: dict[int, Path] = {}
    for path, doc in docs:
        i = doc["shard"]["index"]
        if i in seen:
            raise InputError(f"shard {i}/{count} given twice: {seen[i]} and {path}")
        if doc.get("complete") is not True:
            raise InputError(f"{path}: shard {i}/{count} did not finish ({_cut(repr(doc.get('cases_done')))} of "
                             f"{doc['shard']['cases_total']} cases): run it again")  # fmt: skip
        seen[i] = path
    if len(seen) < count:
        missing = [f"{i}/{count}" for i in range(count) if i not in seen][:_NAMED_MISSING]
        more = count - len(seen) - len(missing)
        raise InputError(f"shard(s) {', '.join(missing)}{f' and {more:,} more' if more else ''} missing: merge needs "
                         f"all {count}")  # fmt: skip
    return count


# ------------------------------------------------------------------------------------------------ the merge
def _check_out_outside(out: Path, folders: list[Path]) -> None:
    """Refuse an ``out`` that is a shard or lies inside one (links resolved): the merge would write into its inputs
    (and a later merge would take its files for the shard's coverage)."""
    where = os.path.realpath(out)
    for folder in folders:
        shard = os.path.realpath(folder)
        if where == shard:
            raise InputError(f"--out {out}: one of the shards; merge into another folder")
        if os.path.commonpath([where, shard]) == shard:
            raise InputError(f"--out {out}: inside the shard {folder}; merge into a folder outside every shard")


def _write_all(files: dict[Path, str]) -> None:
    """Write every file or none: each to a temporary beside it (:func:`~.._atomic.atomic_path`), the temporaries
    renamed onto their names only once all are written (a failed write removes them all)."""
    with contextlib.ExitStack() as stack:
        for path, text in files.items():
            tmp = stack.enter_context(atomic_path(path))
            with open(tmp, "wb") as f:
                f.write(text.encode("utf-8"))
                f.flush()
                os.fsync(f.fileno())


def merge_shards(folders: list[Path], out: Path) -> MergeSummary:
    """Check that ``folders`` are the complete shards of one run, then write the merged run into ``out`` (the
    files of :class:`~.result_files.ResultWriter`, and the first shard's ``coverage/``), all or nothing.

    Raises:
        InputError: a folder that is not a shard, ``out`` inside a shard, a shard file that is a link, not a
            regular file, too large or not a shard's results (naming the file and the field), shards of different
            runs, a missing, repeated or unfinished shard.
    """
    from .result_files import ResultWriter

    docs = [(f, _read(f)) for f in folders]
    _check_out_outside(out, folders)
    _same_run(docs)
    count = _check_complete(docs)
    by_key = {r.case.key: r for folder, doc in docs for r in _results(folder / "results.json", doc)}
    coverage = _read_coverage(docs[0][0])
    first = docs[0][1]
    results = [by_key[k] for k in first["shard"]["case_keys"]]
    config = EvalConfig(baselines=tuple(first["config"].get("baselines", ())))
    run = EvalRun(first["dataset"], first["layout"], first["method"], config, [r.case for r in results], results)
    extra = {k: v for k, v in first.items() if k not in {"dataset", "layout", "method", "context_views", "config",
             "complete", "cases_total", "cases_done", "pending", "errors", "summary", "cases", *_VOLATILE}}  # fmt: skip
    extra["merged_from"] = [str(f) for f in folders]
    writer = ResultWriter(out, extra, config_json=first["config"])
    files = writer.texts(run)
    files.update({check_folder(out / "coverage") / name: text for name, text in coverage.items()})
    _write_all(files)
    return MergeSummary(run, count, len(results))
