"""The summary of an evaluation run: one row per split and method, and its Markdown tables.

Per split (and ``all`` when there are several) and method (:func:`summarize`): image metrics averaged over targets
(the reconstruction and ``points`` over the targets of successful cases, ``copy`` over the targets of all evaluated
cases), median pose and focal errors over successful cases, AUC over successful and failed cases, depth metrics
averaged over successful cases, and the mean reconstruction time; the context views per case and the mean number
of them registered over successful cases. Cases with bad input (status ``"error"``) are counted apart and left out
of every statistic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .metrics import AUC_THRESHOLDS_DEG, pose_auc
from .results import CaseResult, EvalRun
from .splits import SPLITS

__all__ = ["format_cell", "known_mean", "known_median", "summarize", "summary_markdown"]


def known_mean(values: Sequence[float | None]) -> float:
    """Mean of the values that are not None or NaN; NaN when there is none."""
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if len(v) else math.nan


def known_median(values: Sequence[float | None]) -> float:
    """Median of the values that are not None or NaN; NaN when there is none."""
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[~np.isnan(v)]
    return float(np.median(v)) if len(v) else math.nan


_IMAGE_KEYS = ("psnr", "ssim", "psnr_masked", "ssim_masked", "psnr_masked_rgbsum", "lpips", "lpips_masked")


def _image_summary(results: Sequence[CaseResult], method: str) -> dict[str, float]:
    per_target = [t.metrics[method] for r in results for t in r.targets if method in t.metrics]
    out: dict[str, float] = {"targets": len(per_target)}
    for key in _IMAGE_KEYS:
        out[key] = known_mean([m.get(key, math.nan) for m in per_target])
    return out


def summarize(run: EvalRun) -> list[dict[str, Any]]:
    """One row per split (and ``all`` when there are several) and method; see the module docstring."""
    splits = [s for s in SPLITS if any(r.case.split == s for r in run.results)]
    splits += sorted({r.case.split for r in run.results} - set(SPLITS))
    groups = [(s, [r for r in run.results if r.case.split == s]) for s in splits]
    if len(groups) > 1:
        groups.append(("all", list(run.results)))
    rows = []
    for split, results in groups:
        evaluated = [r for r in results if r.status != "error"]
        ok = [r for r in evaluated if r.status == "ok"]
        row: dict[str, Any] = {
            "split": split,
            "method": run.method,
            "cases": len(evaluated),
            "failed": len(evaluated) - len(ok),
            "errors": len(results) - len(evaluated),
            **_image_summary(ok, run.method),
            "rotation_error_deg": known_median([r.rotation_error_deg for r in ok]),
            "translation_error_deg": known_median([r.translation_error_deg for r in ok]),
            **pose_auc([r.pose_error_deg for r in evaluated], AUC_THRESHOLDS_DEG),
            "focal_error_pct": known_median([abs(f) for r in ok for f in r.focal_error_pct if f is not None]),
            "depth_absrel": known_mean([r.depth.get("absrel", math.nan) for r in ok]),
            "depth_delta1": known_mean([r.depth.get("delta1", math.nan) for r in ok]),
            "time_s": known_mean([r.time_s for r in evaluated]),
            "context_views": run.context_views,
            "registered": known_mean([len(r.registered) for r in ok if r.registered is not None]),
        }
        rows.append(row)
        for base in run.config.baselines:
            src = ok if base == "points" else evaluated
            rows.append({"split": split, "method": base, "cases": len(src), **_image_summary(src, base)})
    return rows


def format_cell(v: Any, digits: int = 2) -> str:
    """A table cell: floats to ``digits`` decimals, None/NaN/inf as "–"."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def summary_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The summary as two Markdown tables: novel views per method, then pose, depth and time."""
    views = (
        ("psnr", "PSNR", 2),
        ("ssim", "SSIM", 3),
        ("psnr_masked", "masked PSNR", 2),
        ("ssim_masked", "masked SSIM", 3),
        ("lpips", "LPIPS", 3),
    )
    geo: tuple[tuple[str, str, int], ...] = (
        ("rotation_error_deg", "rot err °", 2), ("translation_error_deg", "t err °", 2), ("auc@5", "AUC@5", 3),
        ("auc@10", "AUC@10", 3), ("auc@20", "AUC@20", 3), ("focal_error_pct", "focal err %", 1),
        ("depth_absrel", "AbsRel", 3), ("depth_delta1", "δ<1.25", 3), ("time_s", "time s", 2),
    )  # fmt: skip
    if any(r.get("context_views", 2) > 2 for r in rows):  # more than two contexts: how many registered
        geo = (*geo, ("registered", f"registered / {max(r.get('context_views', 2) for r in rows)}", 2))
    out = ["| split | method | cases | targets | " + " | ".join(h for _, h, _ in views) + " |"]
    out.append("|---|---|---:|---:|" + "---:|" * len(views))
    for r in rows:
        cells = [r["split"], r["method"], str(r["cases"]), str(r.get("targets", "–"))]
        out.append("| " + " | ".join(cells + [format_cell(r.get(k), d) for k, _, d in views]) + " |")
    out += ["", "| split | ok / cases | " + " | ".join(h for _, h, _ in geo) + " |"]
    out.append("|---|---:|" + "---:|" * len(geo))
    for r in rows:
        if "failed" in r:
            cells = [r["split"], f"{r['cases'] - r['failed']} / {r['cases']}"]
            out.append("| " + " | ".join(cells + [format_cell(r.get(k), d) for k, _, d in geo]) + " |")
    return "\n".join(out) + "\n"
