"""The run report's typed sections: each written as the report has always written it, and the ``reconstruct``
summary table built from the typed report itself (not from its JSON keys)."""

from __future__ import annotations

import json

from macsplat_cli.cli._common import err_console
from macsplat_cli.cli._summary import summary
from macsplat_cli.report import (
    CompactReport,
    CompactStep,
    FillReport,
    FusionReport,
    ImageReport,
    NeuralReport,
    RefineReport,
    RunReport,
)  # fmt: skip


def _report() -> RunReport:
    return RunReport(
        macsplat_version="0", inputs=["/a/left.jpg", "/a/right.jpg"], backends={"pose": "x"},
        times_s={"images": 0.5, "total": 0.5},
        images=[ImageReport("left", [640, 480], [512, 384], "file", 400.0),
                ImageReport("right", [640, 480], [512, 384], "prior", 410.0)],
        keypoints=[900, 800], fallback_used=False, matches={"reciprocal": 300, "verified": 250}, inlier_ratio=0.8,
        pose={"rotation_deg": 12.5, "median_sampson_px": 0.4, "inlier_ratio": 0.8, "median_parallax_deg": 3.0,
              "confidence": 0.9, "doubts": []},
        depth_coverage=[0.9, 0.8], depth_measured=[0.5, None], gaussians=1234, config={},
    )  # fmt: skip


def test_fusion_sections_are_written_in_the_report_order() -> None:
    """The three states of the fusion keep the keys, the values and their order the report has always had."""
    deferred = FusionReport(applied=False, detail="skipped", policy="auto")
    assert list(deferred.to_json().items()) == [("applied", False), ("policy", "auto"), ("detail", "skipped")]
    on_demand = FusionReport(applied=True, detail="ran", policy="auto", on_demand_s=0.5, matches_kept="fused")
    assert list(on_demand.to_json()) == ["applied", "detail", "policy", "on_demand_s", "matches_kept"]
    assert list(FusionReport(applied=True, detail="always").to_json().items()) == [("applied", True),
                                                                                  ("detail", "always")]  # fmt: skip


def test_typed_sections_serialise_to_the_json_document() -> None:
    report = _report()
    report.fill = FillReport(depth=[{"measured": 3}, None])
    step = CompactStep("dedup", 2000, 1234, 0.1, "shared")
    report.add_compact(CompactReport("balanced", 2000, 1234, 3, 3, 0.25, [step]), 1234)
    report.add_network("net on cpu", None, NeuralReport("cpu", "net", [512, 384], 1.5, FusionReport(False, "none"),
                                                        False, {"stride": 4}, {"weights": "w.pth"}, 0.2))  # fmt: skip
    doc = json.loads(json.dumps(report.to_json()))
    assert doc["fill"] == {"depth": [{"measured": 3}, None], "background": None}
    assert doc["compact"]["steps"][0] == {"name": "dedup", "before": 2000, "after": 1234, "seconds": 0.1,
                                          "reason": "shared"}  # fmt: skip
    assert doc["compact"]["ratio"] == 2000 / 1234 and doc["times_s"]["compact"] == 0.25
    assert list(doc["neural"]) == ["device", "network", "network_size", "forward_s", "fusion", "gaussian_head",
                                   "config", "files", "load_s"]  # fmt: skip
    assert doc["backends"]["network"] == "net on cpu" and doc["neural"]["fusion"] == {"applied": False,
                                                                                      "detail": "none"}  # fmt: skip


def test_the_summary_is_built_from_the_typed_report() -> None:
    report = _report()
    report.add_compact(CompactReport("fast", 2000, 1234, 3, 1, 0.25, [CompactStep("dedup", 2000, 1234, 0.1, "")]),
                       1234)  # fmt: skip
    report.add_network("net on cpu", None, NeuralReport("cpu", "net", [512, 384], 1.5,
                                                        FusionReport(True, "DINOv3 fused"), True, {}))  # fmt: skip
    report.add_outputs({"-o": "/o/s.ply"}, gaussians_written=1200)
    with err_console.capture() as got:
        summary(report, {"-o": "/o/s.ply"})
    text = got.get()
    assert "left.jpg: 640x480 → 512x384, focal 400 px (file)" in text
    assert "300 reciprocal → 250 verified" in text and "rotation 12.5°" in text
    assert "1,200: 1,234 of 2,000 kept (fast: dedup −766)" in text and "far layer" not in text
    assert "neural (cpu): forward pass 1.50 s" in text and "DINOv3 fused" in text
    report.add_outputs({"-o": "/o/s.ply"}, gaussians_written=1500)  # the far layer is written beside, not compacted
    with err_console.capture() as got:
        summary(report, {"-o": "/o/s.ply"})
    assert "1,500: 1,234 of 2,000 kept (fast: dedup −766) + far layer 266" in got.get()
    assert "refine" not in got.get()


def test_the_summary_says_how_the_refinement_ran_and_why_at_that_resolution() -> None:
    """Three photos or more: the steps, the resolution the photos chose and their measure; a pair: no measure."""
    report = _report()
    report.add_outputs({"-o": "/o/s.ply"}, gaussians_written=1234)
    for refine, said, unsaid in (
        (RefineReport(8, 8, False, 3.25, 1, True, False, {}, {}, joint={"sharp_gain_db": 0.584}),
         "8 of 8 steps at full resolution, 3.2 s; the photos' sharp Gaussians predict each other +0.58 dB", "stopped"),
        (RefineReport(9, 12, True, 1.5, 2, True, False, {}, {}, joint={"steps": 9}),
         "9 of 12 steps at 1/2 resolution, 1.5 s (stopped: held-out error no longer falling)", "sharp"),
    ):  # fmt: skip
        report.refine = refine
        with err_console.capture() as got:
            summary(report, {"-o": "/o/s.ply"})
        text = " ".join(got.get().replace("│", " ").split())
        assert said in text and unsaid not in text, text
