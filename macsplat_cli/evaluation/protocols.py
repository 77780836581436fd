"""Named evaluation protocols: the choices that make a run comparable with a paper's tables, in one flag.

``mac-splat``: the MAC-Splat authors' released evaluation (``models/mac-splat.md``): ScanNet++ ``nvs_sem_val``
without the scene the release excludes, the published Splatt3R coverage test sets at (0.9, 0.7, 0.5, 0.3) given as
``--cases`` (a folder of ``test_set_*.json``), every 10th row of each, every frame cropped 512×512 about its principal
point (:mod:`.crop`). The metrics are every run's (PSNR over the mask in both formulas, SSIM over the mask as a true
mean, LPIPS over the mask beside the whole-image one).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import InputError

__all__ = ["PROTOCOLS", "EvalProtocol", "get_protocol"]


@dataclass(frozen=True)
class EvalProtocol:
    """Args:
    name: the flag's value.
    every_nth_row: keep every n-th row of each cases file.
    exclude_scenes: scenes left out.
    scannetpp_split: the ScanNet++ split file it evaluates.
    needs_cases: the protocol's cases come from files the user gives (``--cases``).
    cases_hint: what ``--cases`` should be, for the error when it is missing.
    crop: the frames cropped square about the principal point and rescaled to this side (:mod:`.crop`); None: as
        they are.
    """

    name: str
    every_nth_row: int = 1
    exclude_scenes: tuple[str, ...] = ()
    scannetpp_split: str = "nvs_sem_val"
    needs_cases: bool = False
    cases_hint: str = ""
    crop: int | None = None


PROTOCOLS: dict[str, EvalProtocol] = {
    "mac-splat": EvalProtocol(
        name="mac-splat",
        every_nth_row=10,  # the release reads every 10th row of each test set
        exclude_scenes=("cc5237fd77",),  # the release leaves this nvs_sem_val scene out
        scannetpp_split="nvs_sem_val",
        needs_cases=True,
        cases_hint="a folder with Splatt3R's test_set_0.9_0.9.json, test_set_0.7_0.7.json, test_set_0.5_0.5.json "
        "and test_set_0.3_0.3.json",
        crop=512,  # the release's 512x512 crop centred on the principal point
    ),
}


def get_protocol(name: str) -> EvalProtocol:
    """The protocol called ``name`` (InputError naming the known ones)."""
    key = name.strip().lower()
    if key not in PROTOCOLS:
        raise InputError(f"--protocol {name!r}: use one of {', '.join(PROTOCOLS)}")
    return PROTOCOLS[key]
