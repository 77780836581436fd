"""Byte-level fingerprints of `macsplat reconstruct` on the example and the dev scenes: the check that a refactor
changed no output.

    python -m benchmarks.golden --data ../shared/data --json after.json                 # this checkout
    cd /tmp && PYTHONPATH=/tmp/before:$REPO python -m benchmarks.golden --data $DATA --json before.json
    python -m benchmarks.golden --compare before.json after.json                         # exit 1 on a difference

Each case runs the CLI in a subprocess (the checkout that ``macsplat_cli`` imports from) and records its exit code,
the last line of its stderr and the SHA-256 of every file it wrote (scene, cameras, renders; not the report, which
holds times). The cases cover the three quality presets, ``--budget`` with ``--refine``, unknown intrinsics, a
refused pose and ``--accept-low-confidence``. Measured: benchmarks/history/suite.md.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks._common import write_json

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "motorcycle"
CO3D_FOCAL = "1874.6278076171875"  # the CO3D apple frames' focal length (cameras_opencv.json)


def cases(data: Path | None) -> dict[str, list[str]]:
    """Case name → the ``reconstruct`` arguments before ``-o`` (``{o}``: the case's output folder)."""
    ex = [str(EXAMPLE / "left.jpg"), str(EXAMPLE / "right.jpg")]
    known = [*ex, "--intrinsics", str(EXAMPLE / "cameras.json")]
    out = {
        "moto_bal": [*known, "--renders", "{o}/r", "--num-renders", "3"],
        "moto_fast": [*known, "--quality", "fast"],
        "moto_best": [*known, "--quality", "best"],
        "moto_budget_refine": [*known, "--budget", "20000", "--refine", "5", "--size", "256"],
        "moto_noK": ex,
    }
    if data is None:
        return out
    co3d = sorted((data / "co3d_apple" / "images").iterdir())
    icl = data / "icl_nuim_and_home_rgbd" / "icl_livingroom" / "color"
    nyu = data / "icl_nuim_and_home_rgbd" / "nyu_dining" / "color"
    small = ["--size", "384"]
    out.update(
        {
            "co3d_close": [str(co3d[2]), str(co3d[5]), "--focal", CO3D_FOCAL],
            "co3d_medium": [str(co3d[0]), str(co3d[5]), "--focal", CO3D_FOCAL, *small],
            "co3d_wide": [str(co3d[5]), str(co3d[16]), "--focal", CO3D_FOCAL, *small],
            "co3d_vwide_low": [str(co3d[5]), str(co3d[13]), "--focal", CO3D_FOCAL, *small, "--accept-low-confidence"],
            "icl_15": [str(icl / "1.png"), str(icl / "5.png"), "--focal", "481.2"],
            "icl_23_noK": [str(icl / "2.png"), str(icl / "3.png"), *small],
            "nyu_13": [str(nyu / "1.png"), str(nyu / "3.png"), "--focal", "518.0", *small],
        }
    )
    return out


def fingerprint(args: list[str], folder: Path) -> dict[str, object]:
    """Run one case into ``folder``: exit code, stderr's last line, and a hash of every file written."""
    argv = [a.replace("{o}", str(folder)) for a in args]
    cmd = [sys.executable, "-m", "macsplat_cli", "reconstruct", *argv, "-o", str(folder / "scene.ply"),
           "--cameras", str(folder / "cams.json"), "--quiet"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True)
    record: dict[str, object] = {"rc": proc.returncode, "stderr": proc.stderr.strip()[-300:]}
    for f in sorted(p for p in folder.rglob("*") if p.is_file()):
        record[str(f.relative_to(folder))] = hashlib.sha256(f.read_bytes()).hexdigest()[:16]
    return record


def compare(before: Path, after: Path) -> int:
    a, b = json.loads(before.read_text()), json.loads(after.read_text())
    differ = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    for k in differ:
        print(f"{k}: before {a.get(k)}\n{' ' * len(k)}  after  {b.get(k)}")
    print(f"{len(set(a) & set(b))} cases in both, {len(differ)} differ")
    return 1 if differ else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="the shared data folder (../shared/data); none: the example only")
    ap.add_argument("--only", nargs="+", default=[], help="run only these cases")
    ap.add_argument("--json", type=Path, help="write the fingerprints here")
    ap.add_argument("--compare", type=Path, nargs=2, metavar=("BEFORE", "AFTER"), help="compare two --json files")
    args = ap.parse_args()
    if args.compare:
        return compare(*args.compare)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, case in cases(args.data).items():
            if args.only and name not in args.only:
                continue
            folder = Path(tmp) / name
            folder.mkdir()
            results[name] = fingerprint(case, folder)
            print(name, json.dumps(results[name]), flush=True)
    if args.json:
        write_json(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
