"""The first run after an install: the README's first command with an empty Numba cache, against warm runs, and
what compiles (per kernel and signature).

Each run is a fresh process (``python -m macsplat_cli reconstruct <example pair> -o … --renders … --video …``); the
cold one gets a new ``NUMBA_CACHE_DIR``, the warm ones reuse it. Then one more cold run inside a child process
with a listener on Numba's ``numba:compile`` events gives the seconds each kernel took to compile (a kernel's time
includes the functions it inlines or calls that compile with it; library helpers are summed in one row).

    python -m benchmarks.first_run [--warm 2] [--quality balanced]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._common import print_header, row

ROOT = Path(__file__).resolve().parents[1]
PAIR = ("examples/motorcycle/left.jpg", "examples/motorcycle/right.jpg")

_CHILD = r"""
import json, sys, time
from numba.core import event
from macsplat_cli.cli import main
times, starts = {}, {}
class Listener(event.Listener):
    def on_start(self, ev):
        starts[id(ev.data["dispatcher"]), str(ev.data["args"])] = time.perf_counter()
    def on_end(self, ev):
        d = ev.data["dispatcher"]
        dt = time.perf_counter() - starts.pop((id(d), str(ev.data["args"])))
        name = f"{d.py_func.__module__}.{d.py_func.__qualname__}"
        if not name.startswith("macsplat_cli"):
            name = "(Numba library helpers)"
        n, s = times.get(name, (0, 0.0))
        times[name] = (n + 1, s + dt)
event.register("numba:compile", Listener())
t0 = time.perf_counter()
code = main(sys.argv[1:])
print(json.dumps({"code": code, "seconds": time.perf_counter() - t0, "kernels": times}))
"""


def _args(out: Path, quality: str) -> list[str]:
    return ["reconstruct", *PAIR, "-o", str(out / "scene.ply"), "--renders", str(out / "views"),
            "--video", str(out / "scene.mp4"), "--quality", quality, "-q"]  # fmt: skip


def _run(args: list[str], cache: Path, work: Path) -> float:
    out = Path(tempfile.mkdtemp(dir=work))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "macsplat_cli", *_fix(args, out)], cwd=ROOT, env=env, check=True)
    return time.perf_counter() - t0


def _fix(args: list[str], out: Path) -> list[str]:
    return [a.replace("{out}", str(out)) for a in args]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--warm", type=int, default=2, help="warm runs after the cold one [default: 2]")
    p.add_argument("--quality", default="balanced", choices=("fast", "balanced", "best"))
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cli = _args(Path("{out}"), args.quality)
        cache = work / "numba-cache"
        cold = _run(cli, cache, work)
        warm = sorted(_run(cli, cache, work) for _ in range(args.warm))
        median = warm[len(warm) // 2]
        print(f"README's first command (--quality {args.quality}), each run a fresh process, {os.cpu_count()} CPUs\n")
        print_header(["run", "seconds", "× warm"], "lrr")
        print(row(["cold (empty Numba cache)", f"{cold:.2f}", f"{cold / median:.2f}"]))
        for i, s in enumerate(warm):
            print(row([f"warm {i + 1}", f"{s:.2f}", f"{s / median:.2f}"]))
        out = Path(tempfile.mkdtemp(dir=work))
        env = {**os.environ, "NUMBA_CACHE_DIR": str(work / "fresh-cache"), "PYTHONPATH": str(ROOT)}
        res = subprocess.run([sys.executable, "-c", _CHILD, *_fix(cli, out)], cwd=ROOT, env=env, check=True,
                             capture_output=True, text=True)  # fmt: skip
        doc = json.loads(res.stdout.strip().splitlines()[-1])
        total = sum(s for _, s in doc["kernels"].values())
        print(f"\nCompilation on the cold run (in-process {doc['seconds']:.2f} s; compile events {total:.2f} s, "
              "nested compiles counted in their callers too)\n")  # fmt: skip
        print_header(["kernel", "signatures", "seconds"], "lrr")
        for name, (n, s) in sorted(doc["kernels"].items(), key=lambda kv: -kv[1][1]):
            print(row([name.removeprefix("macsplat_cli."), str(n), f"{s:.2f}"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
