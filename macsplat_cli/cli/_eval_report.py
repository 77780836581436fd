"""``eval``'s summary on stderr: the novel-view and geometry tables, the failed cases, the files written."""

from __future__ import annotations

from typing import Any

from ._common import err_console, escape

__all__ = ["print_summary", "summary_tables"]


def summary_tables(rows: list[dict[str, Any]], title: str) -> list[Any]:
    """The summary rows as two Rich tables: novel views (every method), then geometry and time (the backend)."""
    from rich import box
    from rich.table import Table

    from ..evaluation.summary import format_cell

    views = [
        ("split", "split", None), ("method", "method", None), ("cases", "cases", None), ("targets", "targets", None),
        ("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("psnr_masked", "PSNR mask", 2), ("ssim_masked", "SSIM mask", 3),
    ]  # fmt: skip
    views.append(("psnr_masked_rgbsum", "PSNR mask ΣRGB", 2))  # Σ over channels ÷ mask pixels (Splatt3R's)
    if any(r.get("lpips") is not None and r["lpips"] == r["lpips"] for r in rows):  # NaN when not measured
        views += [("lpips", "LPIPS", 3), ("lpips_masked", "LPIPS mask", 3)]
    geometry = [
        ("split", "split", None), ("ok", "ok/cases", None), ("rotation_error_deg", "rot °", 2),
        ("translation_error_deg", "t °", 2), ("auc", "AUC@5/10/20", None), ("focal_error_pct", "focal %", 1),
        ("depth_absrel", "AbsRel", 3), ("depth_delta1", "δ<1.25", 3), ("time_s", "time s", 2),
    ]  # fmt: skip
    n_views = max((r.get("context_views", 2) for r in rows), default=2)
    if n_views > 2:  # more than two contexts: how many of them were registered, on average
        geometry.append(("registered", f"reg./{n_views}", 2))
    backend_rows = [
        {
            **r,
            "ok": f"{r['cases'] - r['failed']}/{r['cases']}",
            "auc": " ".join(format_cell(r.get(f"auc@{t}"), 2) for t in (5, 10, 20)),
        }
        for r in rows
        if "failed" in r
    ]
    tables = []
    for cols, subset, sub in ((views, rows, "novel views"), (geometry, backend_rows, "pose, depth, time")):
        method = f" ({backend_rows[0]['method']})" if sub != "novel views" and backend_rows else ""
        table = Table(
            title=escape(f"{title}: {sub}{method}"),
            title_justify="left",
            box=box.SIMPLE_HEAD,
            pad_edge=False,
            collapse_padding=True,
        )
        for key, head, _ in cols:
            table.add_column(head, justify="left" if key in ("split", "method") else "right", no_wrap=True)
        for row in subset:
            table.add_row(*[escape(format_cell(row.get(key), digits or 0)) for key, _, digits in cols])
        tables.append(table)
    return tables


def print_summary(run: Any, rows: Any, writer: Any, splatt3r_compatible: bool, seconds: float) -> None:
    """The summary tables, the failed cases and the files written, on stderr."""
    mode = "Splatt3R-compatible metrics" if splatt3r_compatible else "standard metrics"
    for table in summary_tables(rows, f"macsplat eval ({mode})"):
        err_console.print(table)
    for r in run.failures:
        failed = escape(f"{r.case.key}: {r.error}")
        err_console.print(f"[yellow]failed[/] {failed}", highlight=False, soft_wrap=True)
    files = f"{writer.json_path}, {writer.csv_path}, {writer.jsonl}"
    err_console.print(
        escape(f"{len(run.results)} case(s) in {seconds:.1f} s; wrote {files}"), highlight=False, soft_wrap=True
    )
