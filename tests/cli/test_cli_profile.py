"""``reconstruct --profile``: a table of each stage's seconds and memory, after the run, also with ``-q``."""

from __future__ import annotations

import re
from pathlib import Path

from support.cli import run_cli
from support.scenes import PairSpec


def test_profile_table_lists_every_stage_with_time_and_memory(pair_files, tmp_path: Path) -> None:  # noqa: ANN001
    pair = pair_files(PairSpec(size=(256, 192)))
    code, out, err = run_cli(["reconstruct", pair.a, pair.b, "-o", tmp_path / "s.ply", "-q", "--profile"])
    assert code == 0 and out == ""
    rows = {m.group(1).strip(): m.groups()[1:] for m in re.finditer(
        r"^(\S[^\d\n]*?)\s+(\d+\.\d{3})\s+(\d+) %\s+([\d,-]+)\s+([\d,]+)", err, re.M)}  # fmt: skip
    for stage in ("start-up (imports, settings)", "images", "descriptors", "matching", "pose", "depth", "gaussians",
                  "compact", "write"):  # fmt: skip
        assert stage in rows, (stage, err)
    total = float(re.search(r"total \(the command\)\s+(\d+\.\d+)", err).group(1))
    stage_sum = sum(float(v[0]) for v in rows.values())
    assert 0 < stage_sum <= total * 1.01  # the stages are parts of the command's time
    peaks = [int(v[3].replace(",", "")) for v in rows.values()]
    assert peaks == sorted(peaks) and peaks[0] > 0  # the peak so far never falls


def test_without_profile_no_table(pair_files, tmp_path: Path) -> None:  # noqa: ANN001
    pair = pair_files(PairSpec(size=(256, 192)))
    code, _, err = run_cli(["reconstruct", pair.a, pair.b, "-o", tmp_path / "s.ply", "-q"])
    assert code == 0 and "where the time and memory went" not in err
