"""Compare two ``--json`` outputs of a benchmark, timings excluded: the check that a change moved no figure.

    python -m benchmarks.compare_json before.json after.json     # exit 1 on any difference

Keys that hold wall time or speed ratios (``time_s``, ``confidence_s``, ``compact_s``, ``render_s``,
``render_cpu_s``, ``speedup``, ``cpu_speedup``, ``seconds``) are dropped at any depth; every other value must be
equal (NaN equals NaN). Prints the number of records and up to 40 differences, each with its JSON path.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

TIMING = frozenset({"time_s", "confidence_s", "compact_s", "render_s", "render_cpu_s", "speedup", "cpu_speedup",
                    "seconds"})  # fmt: skip


def strip(x: Any) -> Any:
    """``x`` without its timing keys, at any depth."""
    if isinstance(x, dict):
        return {k: strip(v) for k, v in x.items() if k not in TIMING}
    if isinstance(x, list):
        return [strip(v) for v in x]
    return x


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Every place where ``a`` and ``b`` differ, as ``path: a vs b``."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}/{k}: only in {'after' if k in b else 'before'}" for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            out += differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        out = [f"{path}: length {len(a)} vs {len(b)}"] if len(a) != len(b) else []
        for i, (x, y) in enumerate(zip(a, b)):
            out += differences(x, y, f"{path}[{i}]")
        return out
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    args = ap.parse_args()
    a, b = (strip(json.loads(p.read_text())) for p in (args.before, args.after))
    found = differences(a, b)
    n = len(a) if isinstance(a, list) else 1
    print(f"{args.before} vs {args.after}: {n} records, {len(found)} differences (timings excluded)")
    for d in found[:40]:
        print("  ", d)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
