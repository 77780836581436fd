"""benchmarks/gsplat_parity.py: its comparison runs (with the plain-PyTorch twin as the peer on the CPU)."""

from __future__ import annotations

import pytest
import torch

from benchmarks import gsplat_parity


def test_parity_table_with_the_torch_twin(capsys: pytest.CaptureFixture[str]) -> None:
    assert gsplat_parity.main(["--peer", "torch", "--sizes", "300:24x16", "--reps", "1"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 300 ")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert float(cells[6]) < 1e-4 and float(cells[8]) > 60  # max abs Δrgb, PSNR: the twins agree
    for cell in cells[9:]:
        cos, norm = (float(v) for v in cell.split("/"))
        assert cos > 0.999 and abs(norm - 1) < 1e-3


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_without_cuda_gsplat_is_not_compared(capsys: pytest.CaptureFixture[str]) -> None:
    assert gsplat_parity.main([]) == 0
    assert "nothing to compare" in capsys.readouterr().out
