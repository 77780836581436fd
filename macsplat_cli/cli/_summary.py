"""``reconstruct``'s summary table on stderr: the photos, the matches, the pose and its confidence, the files; read
from the typed :class:`~macsplat_cli.report.RunReport` (its ``pose`` and ``multiview`` sections are still dicts:
read as their JSON values)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._common import err_console, escape

if TYPE_CHECKING:
    from ..report import RefineReport, RunReport

__all__ = ["summary"]


_TIERS = {
    "wide": "the wide-baseline tier's matches",
    "wide+plane-tiebreak": "the wide-baseline tier: the plane's two poses told apart by the scene off it",
}


def _matches_line(report: RunReport, pose: dict[str, Any]) -> str:
    """The match counts of each step, and which descriptors gave them when it was not the first ones."""
    line = " → ".join(f"{v} {k}" for k, v in report.matches.items())
    tier = _TIERS.get(str(pose.get("descriptors_tier")))
    if tier is None and report.fallback_used:
        tier = "the affine-simulated fallback's matches"
    return line if tier is None else f"{line} ({tier})"


def _photos_line(mv: dict[str, Any]) -> str:
    """More than two photos: how many registered, from which pair, and each photo left out with its reason."""
    photos = mv["photos"]
    ok = sum(p["registered"] for p in photos)
    accepted = sum(p["accepted"] for p in mv["pairs"])
    rms = mv.get("reprojection_rms_px")
    line = (
        f"{ok} of {len(photos)} registered ({accepted} of {len(mv['pairs'])} pairs accepted, first pair "
        f"{' + '.join(mv['init_pair'] or [])}, {mv['points']:,} points, reprojection RMS "
        f"{rms:.2f} px)"
        if rms is not None
        else f"{ok} of {len(photos)} registered"
    )
    left = [f"\n  left out: {p['name']}: {p['reason']}" for p in photos if not p["registered"]]
    return line + "".join(left)


def summary(report: RunReport, written: dict[str, Any]) -> None:
    from rich.table import Table

    from .._json import to_jsonable

    t = Table(title="macsplat reconstruct", show_header=False, title_justify="left")
    t.add_column(style="bold")
    t.add_column()
    t.add_row(
        "images",
        "\n".join(
            f"{escape(Path(p).name)}: {i.original_size[0]}x{i.original_size[1]} → {i.working_size[0]}x"
            f"{i.working_size[1]}, focal {i.focal_px_working:.0f} px ({escape(str(i.intrinsics_source))})"
            for p, i in zip(report.inputs, report.images)
        ),
    )
    mv = to_jsonable(report.multiview) if report.multiview is not None else None
    if mv is not None:
        t.add_row("photos", escape(_photos_line(mv)))
    t.add_row("keypoints", " / ".join(str(k) for k in report.keypoints))
    pose = to_jsonable(report.pose)
    t.add_row("matches" if mv is None else "first pair", escape(_matches_line(report, pose)))
    t.add_row("pose", escape(_pose_line(pose)))
    if pose.get("confidence") is not None or pose.get("doubts"):
        t.add_row("pose check", _pose_check_line(pose))
    if report.neural is not None:
        n = report.neural
        t.add_row("backend", escape(f"neural ({n.device}): forward pass {n.forward_s:.2f} s"))
        t.add_row("fusion", escape(n.fusion.detail))
    t.add_row("depth", " / ".join(f"{100 * c:.0f} %" for c in report.depth_coverage) + " of pixels")
    if report.refine is not None:
        t.add_row("refine", escape(_refine_line(report.refine)))
    t.add_row("Gaussians", escape(_gaussians_line(report)))
    t.add_row("time", escape(", ".join(f"{k} {v:.2f} s" for k, v in report.times_s.items())))
    t.add_row("wrote", "\n".join(escape(str(v)) for v in written.values()))
    err_console.print(t)


def _refine_line(r: RefineReport) -> str:
    """The refinement's steps, resolution and time; where the photos chose the resolution, by how much."""
    scale = "full resolution" if r.scale == 1 else f"1/{r.scale} resolution"
    line = f"{r.steps} of {r.max_steps} steps at {scale}, {r.seconds:.1f} s"
    if r.stopped_early:
        line += " (stopped: held-out error no longer falling)"
    gain = (r.joint or {}).get("sharp_gain_db")
    if gain is not None:  # the photos chose the resolution (presets.refine_for_agreement)
        line += f"; the photos' sharp Gaussians predict each other {gain:+.2f} dB against pooled"
    return line


def _gaussians_line(report: RunReport) -> str:
    """The Gaussians written; with a compaction, what it kept of what it was given and each step's share, and the
    far layer's Gaussians (written beside the compacted ones, never compacted)."""
    written = report.gaussians_written if report.gaussians_written is not None else report.gaussians
    if report.compact is None:
        return f"{written:,}"
    c = report.compact
    changed = ", ".join(f"{s.name} −{s.before - s.after:,}" for s in c.steps if s.before != s.after)
    far = f" + far layer {written - c.after:,}" if written > c.after else ""
    return f"{written:,}: {c.after:,} of {c.before:,} kept ({c.preset}: {changed or 'nothing to remove'}){far}"


def _num(section: dict[str, Any], key: str, fmt: str) -> str:
    v = section.get(key)
    return format(v, fmt) if isinstance(v, (int, float)) else "n/a"


def _pose_line(pose: dict[str, Any]) -> str:
    """Rotation, parallax, inlier ratio, epipolar error (and the metric baseline)."""
    line = (
        f"rotation {_num(pose, 'rotation_deg', '.1f')}°, median parallax {_num(pose, 'median_parallax_deg', '.1f')}°, "
        f"inlier ratio {_num(pose, 'inlier_ratio', '.2f')}, median epipolar error "
        f"{_num(pose, 'median_sampson_px', '.2f')} px"
    )
    if "translation_norm" in pose:
        line += f", baseline {_num(pose, 'translation_norm', '.3f')} m"
    return line


def _pose_check_line(pose: dict[str, Any]) -> str:
    """The acceptance: its confidence and what it weighed, or the warning of a doubted pose kept (markup)."""
    line = f"confidence {_num(pose, 'confidence', '.2f')}"
    ev = pose.get("evidence") or {}
    if isinstance(ev.get("log10_nfa"), (int, float)):  # what the acceptance weighed (issue 25)
        line += (
            f", {ev['inliers']} of {ev['putative_matches']} putative matches ({ev['tier']} tier), "
            f"log10 NFA {ev['log10_nfa']:.0f}, rotation ±{3 * ev['rotation_sigma_deg']:.2f}° (3σ)"
        )
    if pose.get("accepted_low_confidence"):
        return (
            "[yellow]warning: the pose may be wrong (written with --accept-low-confidence): "
            + escape("; ".join(str(d) for d in pose.get("doubts", [])))
            + "[/]"
        )
    return escape(line)
