"""The files of an evaluation run, rewritten after every case so an interrupted run keeps what it finished
(:class:`ResultWriter`): ``cases.jsonl``, ``results.json``, ``results.csv``, ``summary.md`` and ``coverage/``."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._atomic import atomic_write_text, check_folder, check_writable
from .._json import to_jsonable
from ..errors import OutputPathError
from .results import CaseResult, EvalRun
from .summary import summarize, summary_markdown

__all__ = ["CSV_COLUMNS", "ResultWriter", "csv_rows"]

CSV_COLUMNS = (
    "scene", "split", "context_0", "context_1", "target", "target_name", "method", "status",
    "psnr", "ssim", "psnr_masked", "ssim_masked", "lpips", "mask_fraction", "alpha_coverage", "psnr_masked_rgbsum",
    "lpips_masked",
    "rotation_error_deg", "translation_error_deg", "pose_error_deg", "focal_error_pct_0", "focal_error_pct_1",
    "depth_absrel", "depth_delta1", "time_s", "context_views", "contexts", "registered", "error",
)  # fmt: skip
"""The CSV's columns; ``contexts``: every context frame, space-separated (``context_0``, ``context_1``: the first
two); ``registered``: how many of them the reconstruction registered."""


def csv_rows(run: EvalRun) -> list[dict[str, Any]]:
    """One row per (case, target, method); case-level fields on the reconstruction's rows."""
    rows = []
    methods = [run.method, *run.config.baselines]
    for r in run.results:
        c = r.case
        base = {"scene": c.scene, "split": c.split, "context_0": c.context[0], "context_1": c.context[1]}
        case_fields = {
            "status": r.status,
            "rotation_error_deg": r.rotation_error_deg,
            "translation_error_deg": r.translation_error_deg,
            "pose_error_deg": r.pose_error_deg,
            "focal_error_pct_0": r.focal_error_pct[0],
            "focal_error_pct_1": r.focal_error_pct[1],
            "depth_absrel": r.depth.get("absrel"),
            "depth_delta1": r.depth.get("delta1"),
            "time_s": r.time_s,
            "context_views": len(c.context),
            "contexts": " ".join(str(i) for i in c.context),
            "registered": None if r.registered is None else len(r.registered),
            "error": r.error,
        }
        if not r.targets:
            rows.append({**base, "method": run.method, **case_fields})
        for t in r.targets:
            for m in methods:
                metrics = t.metrics.get(m)
                if m != run.method and metrics is None:
                    continue
                row = {**base, "target": t.index, "target_name": t.name, "method": m}
                row.update(case_fields if m == run.method else {"status": r.status if m == "points" else "ok"})
                row.update({k: v for k, v in (metrics or {}).items() if k in CSV_COLUMNS})
                rows.append(row)
    return rows


def _fmt_csv(v: Any) -> Any:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


class ResultWriter:
    """Writes a run's results into a folder after every case.

    Files: ``cases.jsonl`` (one JSON line per finished case), ``results.json`` (settings, summary
    and every case), ``results.csv`` (one row per case, target and method) and ``summary.md`` (the
    summary tables), each rewritten atomically after every case, and ``coverage/<scene>.json``
    when coverage matrices are given.

    ``cases.jsonl`` is rewritten whole rather than appended to: O(cases) per case, as for
    ``results.json`` (which holds the same cases), and in exchange the file is whole at every
    moment (a run killed mid-write leaves no half line) and is never opened in place, so a
    symbolic link or device planted at its name is refused like at any output (:mod:`.._atomic`)
    instead of being written through. ``coverage/`` may not be a link either.
    """

    FILES = ("cases.jsonl", "results.json", "results.csv", "summary.md")
    """The files written into the folder (besides ``coverage/``)."""

    def __init__(
        self, folder: str | Path, extra: dict[str, Any] | None = None, *, config_json: dict[str, Any] | None = None
    ) -> None:
        """``config_json``: the ``config`` to write instead of the run's own (a merge of shards writes theirs)."""
        self.folder = Path(folder)
        self.extra = extra or {}
        self.config_json = config_json
        self.check(self.folder)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputPathError(f"cannot create {self.folder}: {e.strerror or e}") from None
        self.jsonl = self.folder / "cases.jsonl"
        self.json_path = self.folder / "results.json"
        self.csv_path = self.folder / "results.csv"

    @classmethod
    def check(cls, folder: str | Path) -> None:
        """Before any work: every file of :attr:`FILES` can be written (:func:`~.._atomic.check_writable`: no
        link, device or folder at its name) and ``coverage/`` is not a link or a file.

        Raises:
            OutputPathError: naming the file.
        """
        folder = Path(folder)
        for name in cls.FILES:
            check_writable(folder / name)
        check_folder(folder / "coverage")

    def write_coverage(self, coverage: dict[str, np.ndarray], frames: dict[str, list[str]]) -> None:
        for scene, cov in coverage.items():
            doc = {"scene": scene, "frames": frames.get(scene, []), "coverage": np.round(cov, 5).tolist()}
            name = scene.replace("/", "_").replace("\\", "_")  # one file directly in coverage/
            atomic_write_text(check_folder(self.folder / "coverage") / f"{name}.json", json.dumps(doc) + "\n")

    def start(self, run: EvalRun) -> None:
        self.write(run)

    def add(self, run: EvalRun, result: CaseResult) -> None:
        self.write(run)

    def write(self, run: EvalRun) -> None:
        for path, text in self.texts(run).items():
            atomic_write_text(path, text)

    def texts(self, run: EvalRun) -> dict[Path, str]:
        """What :meth:`write` writes: path → text, in the order written (``cases.jsonl`` first)."""
        from dataclasses import asdict, replace

        cases = [r.to_dict() for r in run.results]
        doc = {
            "dataset": run.dataset,
            "layout": run.layout,
            "method": run.method,
            "context_views": run.context_views,
            "config": self.config_json
            if self.config_json is not None
            else to_jsonable({**asdict(replace(run.config, lpips=None)), "lpips": run.config.lpips is not None}),
            **to_jsonable(self.extra),
            "complete": run.complete,
            "cases_total": len(run.cases),
            "cases_done": len(run.results),
            "pending": [c.key for c in run.cases[len(run.results) :]],
            "errors": [{"case": r.case.key, "error": r.error} for r in run.errors],
            "summary": to_jsonable(summarize(run)),
            "cases": cases,
        }
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for row in csv_rows(run):
            w.writerow({k: _fmt_csv(v) for k, v in row.items()})
        return {
            self.jsonl: "".join(json.dumps(c) + "\n" for c in cases),
            self.json_path: json.dumps(doc, indent=1) + "\n",
            self.csv_path: buf.getvalue(),
            self.folder / "summary.md": summary_markdown(doc["summary"]),
        }
